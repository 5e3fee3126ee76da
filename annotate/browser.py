"""Driving the tool in Debian's Chromium with Playwright (browser tests and the workflow
benchmark): offline launch flags and a click at image-pixel coordinates."""
import os

CHROMIUM = "/usr/bin/chromium"
#: no background traffic, and no DNS for anything but this machine
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1, EXCLUDE localhost"]


def missing_browser() -> str | None:
    """Why the browser tests cannot run here, or None."""
    missing = []
    if not os.path.exists(CHROMIUM):
        missing.append(f"{CHROMIUM} (apt-get install -y chromium)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        missing.append("playwright (pip install playwright)")
    return ("needs " + " and ".join(missing)) if missing else None


#: true once the page has shown the server's answer to every action it queued
SETTLED_JS = "() => window.rl && rl.view && !rl.inflight && rl.q.length === 0 && rl.W > 0"
#: true once the status message contains the text and every queued action is answered
UPDATED_JS = ("t => document.querySelector('#message').innerText.includes(t) && window.rl && !rl.inflight && "
              "rl.q.length === 0")


def require_browser() -> None:
    """In a pytest test: skip when the browser is missing, but fail under CI (CI=true)."""
    import pytest

    why = missing_browser()
    if why:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"browser test {why}")
        pytest.skip(f"browser test {why}")


def launch(pw, profile_dir, viewport=(1500, 1350)):
    return pw.chromium.launch_persistent_context(str(profile_dir), executable_path=CHROMIUM, headless=True,
                                                 args=CHROMIUM_FLAGS,
                                                 viewport={"width": viewport[0], "height": viewport[1]})


def wait_ready(page, timeout: float = 30000) -> None:
    """Until the page shows a photo and has no action waiting for the server."""
    page.wait_for_function(SETTLED_JS + " && document.querySelector('#rl-img').complete", polling=20, timeout=timeout)


def image_to_client(page, x: float, y: float) -> tuple[float, float]:
    """Page coordinates of photo pixel (x, y) in the tool's viewer (whatever the zoom and pan)."""
    return tuple(page.evaluate("([x, y]) => rl.toClient(x, y)", [x, y]))


def click_image(page, x: float, y: float, image_width: int | None = None, wait: bool = False) -> None:
    """Click the photo at photo pixel (x, y) (as a labeller would: mouse down and up). With
    `wait`, until the server's answer is on screen. (`image_width` is no longer needed.)"""
    cx, cy = image_to_client(page, x, y)
    vw, vh = page.evaluate("[innerWidth, innerHeight]")
    if not (0 <= cx < vw and 0 <= cy < vh):   # scrolled away (e.g. after typing in a field): scroll back
        page.evaluate("() => document.querySelector('#rl-viewport').scrollIntoView({block: 'center'})")
        cx, cy = image_to_client(page, x, y)
    page.mouse.click(cx, cy)
    if wait:
        page.wait_for_function(SETTLED_JS, polling=10, timeout=15000)
