"""How fast does the annotation tool answer a click? Drives the real UI in Debian's Chromium on a
real photo of a 3-level shelf with 9 boxes (datasets/real-photos/19_..., resized to 1280x960):
4 corners, 3 shelves, the '3' key, 2 clicks per box, 'c' (confirm size), 'd' (done).

Two phases:
* paced: each click waits for the previous answer and then AIM_S (0.5 s, a fast labeller
  aiming), so the round trip of every click is measured alone: click -> the server's answer
  drawn on screen (the page's own timestamps, window.rl.stats); the layouts preview follows
  each answer as a separate step and is timed too;
* burst: 12 clicks 40 ms apart (faster than any labeller); every one must be applied, in order.

Prints median / p90 / max of the round trip and where the time goes: the server's handler
(apply the actions, save, compute outlines, layouts preview and text), gradio's queue and
transport, the page's drawing; then the server-side parts one by one. A person's own time
(aiming: ~1-2 s a click) comes on top; see docs/annotate.md.

    nice -n 10 .venv/bin/python -m bench.speed.annotate_workflow [--screenshot docs/img/annotate.png]
"""
import os
import shutil
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO

PHOTO = REPO / "datasets" / "real-photos" / "19_mock_white_shelf_3lvl.jpg"
W, H = 1280, 960
AIM_S = 0.5
SY = H / 1006  # the clicks below are in the 1280x1006 original's pixels
CORNERS = [(2, 100), (1170, 100), (1170, 885), (2, 885)]
SHELVES = [(600, 872), (600, 575), (600, 242)]
BOXES = [((30, 238), (290, 135)), ((330, 238), (510, 150)), ((730, 238), (915, 135)), ((925, 228), (1165, 105)),
         ((2, 488), (125, 390)), ((140, 488), (385, 385)), ((2, 575), (560, 482)),
         ((355, 795), (550, 660)), ((2, 872), (570, 797))]


def pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def main() -> int:
    os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")
    import cv2
    from playwright.sync_api import sync_playwright

    from annotate import draw as D
    from annotate.app import build_app
    from annotate.browser import SETTLED_JS, click_image, launch, missing_browser, wait_ready
    from annotate.editor import Tool
    from annotate.server import launch_kwargs
    from annotate.store import Project

    why = missing_browser()
    if why:
        print(f"skipped: {why}")
        return 1
    tmp = Path(tempfile.mkdtemp(prefix="annotate-bench-"))
    (tmp / "project").mkdir()
    img = cv2.imread(str(PHOTO))
    cv2.imwrite(str(tmp / "project" / "shelf.jpg"), cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA),
                [cv2.IMWRITE_JPEG_QUALITY, 92])
    project = Project(tmp / "project")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    demo = build_app(project)
    demo.launch(prevent_thread_lock=True, **launch_kwargs("127.0.0.1", port))
    shot = Path(sys.argv[sys.argv.index("--screenshot") + 1]) if "--screenshot" in sys.argv else tmp / "bench.png"
    clicks = keys = 0
    try:
        with sync_playwright() as pw:
            ctx = launch(pw, tmp / "profile")
            page = ctx.new_page()
            t_open = time.perf_counter()
            page.goto(f"http://127.0.0.1:{port}/")
            wait_ready(page)
            t_open = time.perf_counter() - t_open
            t0 = time.perf_counter()

            def click(x, y, wait=True):
                nonlocal clicks
                click_image(page, x, y * SY, wait=wait)
                clicks += 1
                if wait:
                    page.wait_for_timeout(AIM_S * 1000)

            def key(k):
                nonlocal keys
                page.keyboard.press(k)
                keys += 1
                page.wait_for_function(SETTLED_JS, polling=10, timeout=15000)

            for c in CORNERS:
                click(*c)
            for s in SHELVES:
                click(*s)
            key("3")
            for p0, p1 in BOXES:
                click(*p0)
                click(*p1)
            key("c")
            key("d")
            total = time.perf_counter() - t0
            paced = [s for s in page.evaluate("rl.stats") if s["kind"] == "click"]
            page.screenshot(path=str(shot), full_page=True)
            # burst: 12 clicks 40 ms apart in select mode (a click each, nothing saved twice)
            key("4")
            n0 = len(page.evaluate("rl.stats"))
            for k in range(12):
                click(100 + 80 * k, 500, wait=False)
                page.wait_for_timeout(40)
            page.wait_for_function(SETTLED_JS, polling=10, timeout=30000)
            burst = [s for s in page.evaluate("rl.stats")[n0:] if s["kind"] == "click"]
            ctx.close()
    finally:
        demo.close()
    ann = project.load("shelf.jpg")
    rtt = [s["rtt"] for s in paced]
    server = [s["server"] for s in paced]
    answered = [s["answered"] for s in paced]
    print(f"photo {PHOTO.name} resized to {W}x{H}; 3 shelves, {len(BOXES)} boxes; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    print(f"clicks: {clicks - 12} on the photo + {keys - 1} key presses; status {ann['status']}, "
          f"{len(ann['boxes'])} boxes saved")
    print(f"page open (photo sent once): {t_open:.2f} s")
    print(f"round trip per click (click -> answer drawn), paced {AIM_S:g} s apart: median {statistics.median(rtt):.0f} ms, "
          f"p90 {pct(rtt, 0.9):.0f} ms, max {max(rtt):.0f} ms (n={len(rtt)})")
    print(f"  where it goes (medians): server handler {statistics.median(server):.0f} ms, "
          f"gradio queue + transport {statistics.median(a - s for a, s in zip(answered, server)):.0f} ms, "
          f"page drawing to next frame {statistics.median(r - a for r, a in zip(rtt, answered)):.0f} ms")
    print(f"burst: 12 clicks 40 ms apart -> {len(burst)} applied in {len(set(s['batch'] for s in burst))} "
          f"batch size(s) {sorted(set(s['batch'] for s in burst))}; last answered "
          f"{max(s['rtt'] for s in burst):.0f} ms after its click")
    print(f"machine time for the whole photo ({AIM_S:g} s aiming a click): {total:.1f} s")
    tool = Tool(project)
    st = tool.open("shelf.jpg")
    f = tool.frame(st)   # the scene and layouts, built once and shared by the drawing below
    parts = {"frame (scene and layouts, cached)": lambda: tool.frame(st),
             "overlay (outlines)": lambda: D.overlay(f), "layouts preview": lambda: D.preview(f),
             "summary text": lambda: D.summary(f), "header + list statuses": lambda: D.header(tool.frame(st)),
             "save (atomic, version-checked)": lambda: project.save(dict(project.load("shelf.jpg"))),
             "undo history save": lambda: project.save_history("shelf.jpg", 0, st.undo, st.redo)}
    for name, fn in parts.items():
        t = time.perf_counter()
        for _ in range(10):
            fn()
        print(f"  server part: {name}: {(time.perf_counter() - t) * 100:.1f} ms")
    print(f"screenshot: {shot}")
    shutil.rmtree(tmp, ignore_errors=True) if "--screenshot" in sys.argv else None
    return 0


if __name__ == "__main__":
    sys.exit(main())
