"""End to end in a real browser: Debian's Chromium driven by Playwright opens the tool on a real
photo, clicks the rack corners, two shelves and three boxes, checks the live preview, reloads
the page and finds the work restored, marks the image done and exports a dataset that
`racklay check-data` accepts. No request may leave 127.0.0.1.

Needs /usr/bin/chromium (`apt-get install -y chromium`). Skipped without it, except in CI
(CI=true), where a missing browser fails the test."""
import os
import shutil
import socket
import time
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PHOTO = REPO / "datasets" / "real-photos" / "10_loco_orange_crates_a.jpg"
PHOTO_W = 416
# clicks in image pixels (the photo is 416 x 416 and shown at natural size)
# (the right-hand bay, seen obliquely: lowest beam to the third beam)
CORNERS = [(222, 68), (395, 133), (390, 253), (222, 298)]
SHELVES = [(300, 279), (300, 191)]
BOXES = [((228, 297), (262, 232)), ((268, 282), (337, 210)), ((228, 189), (305, 155))]

pytestmark = pytest.mark.browser


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server(tmp_path):
    from annotate.browser import require_browser

    require_browser()
    from annotate.app import build_app, launch_kwargs
    from annotate.store import Project

    proj_dir = tmp_path / "project"
    proj_dir.mkdir()
    shutil.copy(PHOTO, proj_dir / PHOTO.name)
    project = Project(proj_dir)
    demo = build_app(project)
    port = _free_port()
    demo.launch(prevent_thread_lock=True, **launch_kwargs("127.0.0.1", port))
    yield project, f"http://127.0.0.1:{port}/"
    demo.close()


def test_annotate_in_browser(server, tmp_path):
    from playwright.sync_api import expect, sync_playwright

    from annotate.browser import click_image, launch
    from annotate.cli import main as annotate_main
    from racklay.data import check_dataset
    from racklay.viz import PALETTE

    project, url = server
    hosts = set()
    timings = {}
    with sync_playwright() as pw:
        ctx = launch(pw, tmp_path / "chrome-profile")
        try:
            page = ctx.new_page()
            page.on("request", lambda r: hosts.add(urlparse(r.url).hostname))
            t0 = time.perf_counter()
            page.goto(url)
            header, message, summary = page.locator("#header"), page.locator("#message"), page.locator("#summary")
            expect(header).to_contain_text("0 of 1 done", timeout=20000)
            img = page.locator("#photo img")
            expect(img).to_be_visible()

            def click(x, y, expect_msg):
                click_image(page, x, y, PHOTO_W)
                expect(message).to_contain_text(expect_msg, timeout=10000)

            t1 = time.perf_counter()
            for k, (x, y) in enumerate(CORNERS[:3]):
                click(x, y, f"corner {k + 1} of 4")
            click(*CORNERS[3], "4 corners set")
            for k, (x, y) in enumerate(SHELVES):
                click(x, y, f"shelf {k + 1} marked")
            page.keyboard.press("3")  # shortcut: boxes mode
            expect(page.locator("#mode-help")).to_contain_text("boxes")
            for k, (p0, p1) in enumerate(BOXES):
                click(*p0, "opposite corner")
                click(*p1, f"box {k} added")
            timings["clicks"] = time.perf_counter() - t1
            # live check: both shelves listed with boxes, the preview shows box pixels
            expect(summary).to_contain_text("S2")
            text = summary.inner_text()
            assert "S1" in text and "2 box(es)" in text and "1 box(es)" in text, text
            src = page.locator("#preview img").get_attribute("src")
            import cv2
            pv = cv2.imdecode(np.frombuffer(page.request.get(src).body(), np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
            assert (np.abs(pv.astype(int) - PALETTE[2]).sum(axis=2) == 0).sum() > 200  # box colour present
            assert (np.abs(pv.astype(int) - PALETTE[1]).sum(axis=2) == 0).sum() > 200  # shelf colour present
            # typing into a field applies on Enter and is not taken as shortcuts ("5" = move mode)
            field = page.locator("#rack-depth input")
            field.fill("0.55")
            field.press("Enter")
            expect(summary).to_contain_text("× 0.55 m")
            expect(page.locator("#mode-help")).to_contain_text("boxes")
            # undo / redo by keyboard
            page.locator("#header").click()  # focus back on the page
            page.keyboard.press("z")
            expect(message).to_contain_text("undone")
            page.keyboard.press("y")
            expect(message).to_contain_text("redone")
            # reload: the work is restored from disk
            page.reload()
            expect(header).to_contain_text("in progress", timeout=20000)
            expect(summary).to_contain_text("S2")
            text2 = summary.inner_text()
            assert "2 box(es)" in text2 and "1 box(es)" in text2 and "4/4 corners" in text2, text2
            shots = [tmp_path / "annotate.png"] + ([Path(os.environ["ANNOTATE_SCREENSHOT"])]
                                                    if os.environ.get("ANNOTATE_SCREENSHOT") else [])
            for s in shots:
                page.screenshot(path=str(s), full_page=True)
            page.keyboard.press("d")
            expect(header).to_contain_text("1 of 1 done")
            timings["total"] = time.perf_counter() - t0
        finally:
            ctx.close()
    print(f"\nbrowser timings: {timings}")
    ann = project.load(PHOTO.name)
    assert ann["status"] == "done" and len(ann["boxes"]) == 3 and len(ann["shelves"]) == 2
    out = tmp_path / "dataset"
    assert annotate_main(["export", str(project.root), "--out", str(out), "--split", "train=1"]) == 0
    rep = check_dataset(out)
    assert rep.ok and rep.samples == 1, rep.problems
    assert hosts == {"127.0.0.1"}, hosts
