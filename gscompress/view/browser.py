"""Drive the viewer's page in headless Chromium (playwright over the system's Chromium, WebGL
in software): what its test, its benchmark and `make screenshot` share.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")
"""Executables tried for the browser (Debian's package installs `chromium`)."""

CHROMIUM_FLAGS = ("--ignore-gpu-blocklist", "--no-sandbox")
"""WebGL on a machine without a GPU, and no sandbox (CI containers run as root)."""

GL_FLAGS = {
    "swiftshader": ("--use-angle=swiftshader", "--enable-unsafe-swiftshader"),
    "llvmpipe": ("--use-angle=gl-egl",),
}
"""Software WebGL for the page: Chromium's own SwiftShader (always there; the tests use it), or
Mesa's llvmpipe through EGL (Debian `libegl-mesa0`; Chromium falls back to no WebGL without
it). On a 2-core machine llvmpipe draws viser's page faster (docs/viewer.md, "Smaller frames
while moving, and the page's WebGL")."""


def find_chromium() -> str | None:
    """The path of a Chromium executable, or None."""
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


def missing() -> str | None:
    """Why the viewer cannot be driven here (a missing piece), or None when it can."""
    for module, extra in (("viser", "[view]"), ("playwright", "[dev]")):
        try:
            __import__(module)
        except ImportError:
            return f"{module} is not installed (pip install 'gscompress{extra}')"
    if find_chromium() is None:
        return "no Chromium found (Debian: apt-get install chromium)"
    return None


@contextmanager
def open_page(
    url: str, width: int = 1280, height: int = 720, gl: str = "swiftshader"
) -> Iterator[tuple[Any, list[str]]]:
    """A headless Chromium page at `url`, its WebGL drawn by `gl` (a `GL_FLAGS` key), and the
    console errors it logs (page errors too)."""
    from playwright.sync_api import sync_playwright

    executable = find_chromium()
    if executable is None:
        raise RuntimeError(missing() or "no Chromium")
    errors: list[str] = []
    with sync_playwright() as p:
        flags = [*CHROMIUM_FLAGS, *GL_FLAGS[gl]]
        browser = p.chromium.launch(executable_path=executable, args=flags)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            yield page, errors
        finally:
            browser.close()


def dismiss_notices(page: Any) -> None:
    """Close the page's notices (viser's note that WebGL runs in software, here by design)."""
    buttons = page.locator(".mantine-Notification-closeButton")
    for i in reversed(range(buttons.count())):
        buttons.nth(i).click()


def wait_for_text(page: Any, text: str, timeout_s: float = 30.0) -> float:
    """Seconds until `text` shows on the page (TimeoutError past `timeout_s`)."""
    started = time.perf_counter()
    page.get_by_text(text).first.wait_for(timeout=timeout_s * 1000)
    return time.perf_counter() - started


def slider_input(page: Any, label: str) -> Any:
    """The number box beside the viser slider labelled `label` (typing in it moves it)."""
    return page.locator(
        f"xpath=//label[text()='{label}']/ancestor::div[contains(@class, 'mantine-Flex-root')]"
        "[1]//input[contains(@class, 'mantine-NumberInput-input')]"
    )


def set_slider(page: Any, label: str, value: float) -> None:
    """Move the slider labelled `label` to `value`, as a user typing it in."""
    box = slider_input(page, label)
    box.fill(f"{value:g}")
    box.press("Enter")


def canvas_spread(png: bytes) -> tuple[int, float]:
    """Distinct colours and the standard deviation of the pixels of a screenshot (a blank
    page has one colour and no spread)."""
    import io

    import numpy as np
    from PIL import Image

    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3)
    return len(np.unique(pixels, axis=0)), float(pixels.std())
