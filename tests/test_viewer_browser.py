"""End to end: `slamreloc view` on a synthetic map, opened in headless Chromium (Debian's
package, driven by Playwright). Checks that the page renders the map's points, that the step
button changes the frame image, that the page fetches nothing from outside, and that Ctrl-C
ends the server cleanly. Skips with a reason only where Chromium cannot be had."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pytest

from tests import browser as browser_helpers
from tests.browser import chromium_context, dismiss_notifications, drawn_fraction, find_chromium
from tests.conftest import sigint_as_from_a_terminal

ROOT = Path(__file__).resolve().parents[1]


def chromium_or_skip() -> str:
    """Debian's chromium; installed with apt-get when missing and this runs as root."""
    path = find_chromium()
    if path is None and hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        try:
            subprocess.run(["apt-get", "update", "-qq"], env=env, timeout=300,
                           capture_output=True)
            subprocess.run(["apt-get", "install", "-y", "-qq", "chromium"], env=env,
                           timeout=600, capture_output=True)
        except (OSError, subprocess.TimeoutExpired):
            pass
        path = find_chromium()
    if path is None:
        pytest.skip("no chromium browser (apt-get install chromium needs root and Debian's "
                    "package archive)")
    return path


@pytest.fixture(scope="module")
def browser():
    path = chromium_or_skip()
    pytest.importorskip("playwright.sync_api",
                        reason="playwright not installed (pip install playwright)")
    with chromium_context(path) as ctx:
        yield ctx


def start_view(args: list[str], port: int) -> tuple[subprocess.Popen, str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "slamreloc.cli", "view", *args,
                             "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=ROOT, env=env,
                            preexec_fn=sigint_as_from_a_terminal)
    deadline = time.time() + 90
    seen = []
    while time.time() < deadline:
        line = proc.stdout.readline()
        if not line and proc.poll() is not None:
            break
        seen.append(line)
        if line.startswith("viewer: http://"):
            return proc, line.split()[1]
    proc.kill()
    pytest.fail("slamreloc view printed no address:\n" + "".join(seen))


def wait_rendered(page, timeout: float = 90.0, min_fraction: float = 0.02) -> np.ndarray:
    try:
        return browser_helpers.wait_rendered(page, timeout, min_fraction)
    except TimeoutError as err:
        pytest.fail(str(err))


def test_view_renders_map_and_slider_changes_image(viewer_case, browser, tmp_path):
    with socket.socket() as busy:  # the asked port is taken: the printed address must say so
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc, url = start_view([str(viewer_case.map_dir), "--trajectory",
                                str(viewer_case.trajectory), "--report", str(viewer_case.report),
                                "--report", str(viewer_case.slam_report)], port)
        try:
            assert urlparse(url).hostname == "127.0.0.1"
            assert urlparse(url).port != port
            page = browser.new_page()
            hosts = set()
            page.on("request", lambda r: hosts.add(urlparse(r.url).netloc)
                    if r.url.startswith(("http", "ws")) else None)
            page.goto(url)
            page.wait_for_selector("canvas", timeout=30000)
            dismiss_notifications(page)
            shot = wait_rendered(page)
            page.screenshot(path=str(tmp_path / "viewer.png"))
            # not blank: many pixels drawn, in many colours
            assert drawn_fraction(shot) > 0.03
            assert len(np.unique(shot.reshape(-1, 3) // 16, axis=0)) > 30
            # the map's points are visible: hiding their layer removes many drawn pixels
            page.get_by_label("map points").click()
            hidden = wait_rendered(page, min_fraction=0.0)
            changed = np.abs(shot.astype(int) - hidden).max(axis=2) > 40
            assert changed.mean() > 0.01, f"points cover {changed.mean():.4f} of the canvas"
            assert drawn_fraction(hidden) < drawn_fraction(shot)
            page.get_by_label("map points").click()
            # the step button moves the frame slider: the frame image changes
            frame_img = page.locator("img[src^='blob:']").first
            frame_img.wait_for(timeout=10000)
            before = frame_img.get_attribute("src")
            pixels_before = frame_img.screenshot()
            page.get_by_role("button", name="step ▶").click()
            page.wait_for_function(
                "src => { const i = document.querySelector(\"img[src^='blob:']\");"
                " return i && i.src !== src && i.complete; }", arg=before, timeout=10000)
            time.sleep(0.3)
            assert frame_img.screenshot() != pixels_before
            assert page.get_by_text("(2/18)").count() == 1  # the frame text follows the slider
            assert page.get_by_role("button", name="Share").count() == 0
            assert hosts and hosts <= {urlparse(url).netloc}, hosts
            page.close()
        finally:
            proc.send_signal(signal.SIGINT)  # Ctrl-C
            try:
                out, _ = proc.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                raise
        assert proc.returncode == 0, out
        assert "viewer stopped" in out
