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


#: true once the status message contains the text and the new photo has loaded
UPDATED_JS = ("t => document.querySelector('#message').innerText.includes(t) && "
              "(e => e && e.complete && e.naturalWidth > 0)(document.querySelector('#photo img'))")


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


def click_image(page, x: float, y: float, image_width: int, selector: str = "#photo img") -> None:
    """Click the photo at image pixel (x, y): accounts for the tool enlarging small photos and
    the browser shrinking large ones (object-fit: scale-down, centred)."""
    page.wait_for_function("s => { const e = document.querySelector(s); return e && e.complete && e.naturalWidth > 0; }",
                           arg=selector, polling=10)
    img = page.locator(selector)
    box = img.bounding_box()
    nw, nh = img.evaluate("e => [e.naturalWidth, e.naturalHeight]")
    s = min(1.0, box["width"] / nw, box["height"] / nh)
    ox, oy = (box["width"] - nw * s) / 2, (box["height"] - nh * s) / 2
    k = nw / image_width
    page.mouse.click(box["x"] + ox + (x + 0.5) * k * s, box["y"] + oy + (y + 0.5) * k * s)
