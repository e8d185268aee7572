"""Drive the viewer in a headless browser: Debian's ``chromium`` with software WebGL (SwiftShader)
through selenium and ``chromedriver``: helpers of the browser test and the viewer benchmark, kept
with the tests (not shipped in the package).

Needs ``apt-get install -y chromium chromium-driver`` and ``pip install selenium`` (in the
``test`` extra). Playwright's own browser download is not used (it needs the internet); the
flags below let chromium run as root, offline, with a throw-away profile.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Optional

import numpy as np

__all__ = ["CHROMIUM", "CHROMEDRIVER", "browser_missing", "chromium_driver", "stable_render",
           "fit_canvas_aspect", "compare_frames", "serve_folder"]

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
CHROMIUM_FLAGS = ("--headless=new", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                  "--force-device-scale-factor=1")


def browser_missing() -> Optional[str]:
    """Why a headless browser cannot be driven here (None: it can)."""
    for mod in ("viser", "selenium"):
        try:
            __import__(mod)
        except ImportError:
            return f"{mod} not installed (pip install -e '.[test]')"
    for exe in (CHROMIUM, CHROMEDRIVER):
        if not os.access(exe, os.X_OK):
            return f"{exe} not found (apt-get install -y chromium chromium-driver)"
    return None


def chromium_driver(profile_dir: os.PathLike | str, window: tuple[int, int] = (960, 600)):
    """A selenium WebDriver on headless chromium with a fresh profile in ``profile_dir``.
    The caller quits it (``driver.quit()``)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    Path(profile_dir).mkdir(parents=True, exist_ok=True)
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in CHROMIUM_FLAGS + (f"--user-data-dir={profile_dir}", f"--window-size={window[0]},{window[1]}"):
        opts.add_argument(a)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)


def canvas_size(driver) -> tuple[int, int]:
    """(width, height) in CSS pixels of the page's largest canvas (viser's 3D view)."""
    w, h = driver.execute_script(
        "var c = [...document.querySelectorAll('canvas')].sort((a, b) => b.width * b.height - a.width * a.height)[0];"
        "var r = c.getBoundingClientRect(); return [r.width, r.height];")
    return int(round(w)), int(round(h))


def fit_canvas_aspect(driver, width: int, height: int) -> tuple[int, int]:
    """Resize the window so the canvas is ``width`` x ``height`` CSS pixels (the window chrome
    is measured, not assumed); returns the canvas size reached."""
    for _ in range(3):
        cw, ch = canvas_size(driver)
        if (cw, ch) == (width, height):
            break
        ww, wh = driver.execute_script("return [window.outerWidth, window.outerHeight]")
        driver.set_window_size(ww + width - cw, wh + height - ch)
    return canvas_size(driver)


def stable_render(client, height: int, width: int, timeout: float = 120.0, tries: int = 6, **pose) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1]: the browser's frame (``client.get_render``, lossless PNG) at
    the client's camera or at ``pose`` (``wxyz``, ``position``, ``fov``), repeated until two
    consecutive frames agree (viser sorts splats in a web worker, so the first frame after an
    update may still use the old order)."""
    prev = client.get_render(height, width, transport_format="png", timeout=timeout, **pose)
    for _ in range(tries):
        cur = client.get_render(height, width, transport_format="png", timeout=timeout, **pose)
        if np.array_equal(cur, prev):
            break
        prev = cur
    return cur[..., :3].astype(np.float32) / 255.0


def compare_frames(ours: np.ndarray, theirs: np.ndarray, lit: float = 2 / 255) -> dict:
    """How far two [H, W, 3] images in [0, 1] on a black background differ.

    Returns:
        ``psnr`` (dB, whole frame), ``psnr_covered`` (dB over the pixels where either image
        exceeds ``lit`` in some channel: the splats, not the empty background), ``mad`` (mean
        absolute difference, whole frame) and ``covered`` (that pixel share).
    """
    covered = (ours.max(-1) > lit) | (theirs.max(-1) > lit)
    d2 = (ours.astype(np.float64) - theirs) ** 2
    cov_mse = d2[covered].mean() if covered.any() else 0.0
    return {"psnr": float(10 * np.log10(1 / max(d2.mean(), 1e-12))),
            "psnr_covered": float(10 * np.log10(1 / max(cov_mse, 1e-12))),
            "mad": float(np.abs(ours.astype(np.float64) - theirs).mean()), "covered": float(covered.mean())}


def serve_folder(root: os.PathLike | str):
    """A context manager serving ``root`` over http on 127.0.0.1 (a free port; requests not
    logged), yielding the base URL: module scripts and fetches need http, not file://."""
    import contextlib
    import functools
    import threading
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    @contextlib.contextmanager
    def run():
        srv = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(root)))
        t = threading.Thread(target=srv.serve_forever, daemon=True)
        t.start()
        try:
            yield f"http://127.0.0.1:{srv.server_address[1]}"
        finally:
            srv.shutdown()
            srv.server_close()

    return run()
