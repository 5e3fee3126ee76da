"""How long does a typical photo take in the annotation tool? Drives the real UI in Chromium
on a real 1280x1006 photo of a 3-level shelf with 9 boxes (datasets/real-photos/19_...):
4 corners, 3 shelves, the '3' key, 2 clicks per box, 'd' (done). Prints the number of clicks and
keys, the server round trip per click (click -> the page shows the result) and the total.
A person's own time (aiming: ~1-2 s a click) comes on top; see docs/annotate.md.

    nice -n 10 .venv/bin/python bench/annotate_workflow.py [--screenshot docs/img/annotate.png]
"""
import shutil
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PHOTO = REPO / "datasets" / "real-photos" / "19_mock_white_shelf_3lvl.jpg"
W = 1280
CORNERS = [(2, 100), (1170, 100), (1170, 885), (2, 885)]
SHELVES = [(600, 872), (600, 575), (600, 242)]
BOXES = [((30, 238), (290, 135)), ((330, 238), (510, 150)), ((730, 238), (915, 135)), ((925, 228), (1165, 105)),
         ((2, 488), (125, 390)), ((140, 488), (385, 385)), ((2, 575), (560, 482)),
         ((355, 795), (550, 660)), ((2, 872), (570, 797))]


def main() -> int:
    from playwright.sync_api import expect, sync_playwright

    from annotate.app import Tool, build_app, launch_kwargs
    from annotate.browser import UPDATED_JS, click_image, launch, missing_browser
    from annotate.store import Project

    why = missing_browser()
    if why:
        print(f"skipped: {why}")
        return 1
    tmp = Path(tempfile.mkdtemp(prefix="annotate-bench-"))
    (tmp / "project").mkdir()
    shutil.copy(PHOTO, tmp / "project" / PHOTO.name)
    project = Project(tmp / "project")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    demo = build_app(project)
    demo.launch(prevent_thread_lock=True, **launch_kwargs("127.0.0.1", port))
    lat, clicks, keys = [], 0, 0
    try:
        with sync_playwright() as pw:
            ctx = launch(pw, tmp / "profile")
            page = ctx.new_page()
            page.goto(f"http://127.0.0.1:{port}/")
            msg = page.locator("#message")
            expect(page.locator("#header")).to_contain_text("0 of 1 done", timeout=30000)
            t0 = time.perf_counter()

            def click(x, y, want):
                nonlocal clicks
                t = time.perf_counter()
                click_image(page, x, y, W)
                page.wait_for_function(UPDATED_JS, arg=want, polling=10, timeout=15000)
                lat.append(time.perf_counter() - t)
                clicks += 1

            for k, c in enumerate(CORNERS):
                click(*c, "4 corners set" if k == 3 else f"corner {k + 1} of 4")
            for k, s in enumerate(SHELVES):
                click(*s, f"shelf {k + 1} marked")
            page.keyboard.press("3")
            keys += 1
            expect(page.locator("#mode-help")).to_contain_text("boxes")
            for k, (p0, p1) in enumerate(BOXES):
                click(*p0, "opposite corner")
                click(*p1, f"box {k} added")
            page.keyboard.press("d")
            keys += 1
            expect(page.locator("#header")).to_contain_text("1 of 1 done")
            total = time.perf_counter() - t0
            shot = Path(sys.argv[sys.argv.index("--screenshot") + 1]) if "--screenshot" in sys.argv else tmp / "bench.png"
            page.screenshot(path=str(shot), full_page=True)
            ctx.close()
    finally:
        demo.close()
    tool = Tool(project)
    st = tool.open(PHOTO.name)
    t = time.perf_counter()
    for _ in range(10):
        tool.render_photo(st), tool.render_preview(st), tool.summary(st), tool.header(st)
    server = (time.perf_counter() - t) / 10
    ann = project.load(PHOTO.name)
    _, top, front = tool.layouts(ann)
    print(f"photo {PHOTO.name} ({W}x1006), 3 shelves, {len(BOXES)} boxes")
    print(f"clicks: {clicks} on the photo + {keys} key presses")
    print(f"round trip per click (click -> page updated): median {statistics.median(lat) * 1000:.0f} ms, "
          f"mean {statistics.mean(lat) * 1000:.0f} ms, max {max(lat) * 1000:.0f} ms")
    print(f"server-side redraw (photo overlay + layouts + text) per action: {server * 1000:.0f} ms")
    print(f"machine time for the whole photo: {total:.1f} s (clicks issued back to back)")
    print(f"boxes per shelf: {[int(sum(b.shelf == i for b in tool.layouts(ann)[0].boxes)) for i in range(3)]}")
    print(f"screenshot: {shot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
