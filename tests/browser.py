"""Headless Chromium on the viewer's page (Debian's `chromium`, driven by Playwright): software
WebGL (SwiftShader), no network besides the page itself. Used by the browser test,
benchmarks/viewer_benchmark.py and scripts/viewer_screenshot.py."""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

FLAGS = ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--no-first-run", "--disable-dev-shm-usage"]
VIEWPORT = {"width": 1280, "height": 800}
CANVAS_WIDTH = 900  # the control panel covers the right of the page


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return None


@contextmanager
def chromium_context(path: str | None = None, viewport: dict | None = None,
                     scale: float = 1.0) -> Iterator[object]:
    """A Playwright browser context on a fresh profile (removed afterwards)."""
    from playwright.sync_api import sync_playwright

    path = path or find_chromium()
    if path is None:
        raise RuntimeError("no chromium browser (apt-get install chromium)")
    with sync_playwright() as p:
        profile = tempfile.mkdtemp(prefix="slamreloc-chromium-")
        ctx = p.chromium.launch_persistent_context(
            profile, executable_path=path, headless=True, args=FLAGS,
            viewport=viewport or VIEWPORT, device_scale_factor=scale)
        try:
            yield ctx
        finally:
            ctx.close()
            shutil.rmtree(profile, ignore_errors=True)


def decode_png(png: bytes) -> np.ndarray:
    """RGB uint8 image of PNG bytes."""
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def canvas_shot(page, width: int = CANVAS_WIDTH, timeout_ms: float = 30_000) -> np.ndarray:
    """The 3D view left of the control panel, as RGB."""
    size = page.viewport_size or VIEWPORT
    return decode_png(page.screenshot(clip={"x": 0, "y": 0, "width": width,
                                            "height": size["height"]}, timeout=timeout_ms))


def drawn_fraction(img: np.ndarray) -> float:
    """Share of pixels that differ from the page's (near-white) background."""
    return float((np.abs(img.astype(int) - 255).max(axis=2) > 40).mean())


def wait_rendered(page, timeout: float = 90.0, min_fraction: float = 0.02,
                  width: int = CANVAS_WIDTH) -> np.ndarray:
    """Poll screenshots until the canvas shows something and has stopped changing; the last
    one. TimeoutError when it does not within `timeout` seconds."""
    deadline, last = time.time() + timeout, None
    while time.time() < deadline:
        img = canvas_shot(page, width)
        if drawn_fraction(img) > min_fraction and last is not None and \
                np.abs(img.astype(int) - last).max(axis=2).astype(bool).mean() < 0.002:
            return img
        last = img.astype(int)
        time.sleep(0.5)
    raise TimeoutError(f"the scene did not render within {timeout} s (drawn fraction "
                       f"{drawn_fraction(canvas_shot(page, width)):.4f})")


def dismiss_notifications(page) -> None:
    for button in page.locator("button.mantine-Notification-closeButton").all():
        try:
            button.click(timeout=2000)
        except Exception:  # noqa: BLE001 - a notification may close by itself
            pass
