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
           "fit_canvas_aspect", "compare_frames", "serve_folder", "open_web_viewer", "web_viewer_frame", "web_viewer_popping", "frame_change"]

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
CHROMIUM_FLAGS = ("--headless=new", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                  "--force-device-scale-factor=1")


def browser_missing(modules: tuple = ("viser", "selenium")) -> Optional[str]:
    """Why a headless browser cannot be driven here (None: it can); ``modules``: the Python
    packages the caller needs besides chromium and chromedriver."""
    for mod in modules:
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


def open_web_viewer(driver, url: str, timeout: float = 180.0) -> None:
    """Load a ``clod-export --web`` page and wait until its model is on the GPU
    (``window.__clodReady``)."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get(url)
    WebDriverWait(driver, timeout, poll_frequency=0.5).until(
        lambda d: d.execute_script("return window.__clodReady === true"))


def web_viewer_frame(driver, s_v: Optional[float] = None, static: Optional[bool] = None,
                     settle: int = 3, timeout: float = 120.0, budget: Optional[int] = None) -> tuple[np.ndarray, dict]:
    """Set the page's level and/or static toggle (or, a merge tree's page, a count ``budget`` of
    drawn nodes in view), let ``settle`` frames render, and return ([H, W, 3] float32 canvas in
    [0, 1], the page's state: ``sv``, ``drawn``, ``inFrustum``, ``level``, ``frameMs``, ...)."""
    import base64
    import io
    import json
    import time

    from PIL import Image

    if s_v is not None:
        driver.execute_script(f"window.clod.setSv({float(s_v)})")
    if static is not None:
        driver.execute_script(f"window.clod.setStatic({'true' if static else 'false'})")
    if budget is not None:
        driver.execute_script(f"window.clod.setBudget({int(budget)})")
    f0 = driver.execute_script("return window.clod.frames()")
    t0 = time.monotonic()
    while driver.execute_script("return window.clod.frames()") < f0 + settle:
        if time.monotonic() - t0 > timeout:
            raise TimeoutError("the page stopped rendering")
        time.sleep(0.05)
    data = driver.execute_script("return document.getElementById('c').toDataURL('image/png')")
    img = Image.open(io.BytesIO(base64.b64decode(data.split(",", 1)[1]))).convert("RGB")
    state = json.loads(driver.execute_script("return JSON.stringify(window.clod.state)"))
    return np.asarray(img, dtype=np.float32) / 255.0, state


def frame_change(a: np.ndarray, b: np.ndarray) -> float:
    """:func:`clod_adapter.jobs.eval.image_change` (clod-eval's popping step: mean |dI|) of two
    [H, W, 3] float images in [0, 1]."""
    import torch

    from clod_adapter.jobs.eval import image_change

    return image_change(torch.from_numpy(a), torch.from_numpy(b))


def web_viewer_popping(driver, max_sv: float, steps: int = 31, s_vs: Optional[list] = None,
                       budgets: Optional[list] = None) -> dict:
    """The popping measure of ``clod-eval`` (:func:`clod_adapter.jobs.eval.popping_curve`) in a
    ``clod-export --web`` page, from its current camera: ``steps`` frames at ``s_v`` spaced
    linearly from 1 to ``max_sv`` (or at ``s_vs``, or within the count ``budgets`` of a merge
    tree's page) against one switch between the page's static cuts at the first and the last
    frame's drawn counts (a merge tree's page has no static cut: ``jump`` and ``ratio`` None).

    Returns:
        ``s_v`` [steps], ``drawn`` [steps], ``ms`` [steps] (the page's median frame time after
        each step), ``level`` [steps] (the page's level of the gains; a merge tree's page: the level drawn), ``frames`` [steps] images, ``step`` [steps - 1] mean |dI| between consecutive
        frames, ``jump`` (the static switch's mean |dI|) and ``ratio`` = jump / max(step).
    """
    tree = budgets is not None or bool(driver.execute_script("return window.clod.state.tree !== null"))
    if s_vs is None and budgets is None:
        s_vs = [1.0 + (max_sv - 1.0) * i / (steps - 1) for i in range(steps)]
    frames, drawn, ms, levels = [], [], [], []
    for x in budgets if budgets is not None else s_vs:
        img, st = (web_viewer_frame(driver, budget=x) if budgets is not None
                   else web_viewer_frame(driver, s_v=x, static=None if tree else False))
        frames.append(img)
        drawn.append(st["drawn"])
        ms.append(st["frameMs"])
        levels.append(st["sv"] if tree else st["level"])
    change = frame_change
    step = [change(a, b) for a, b in zip(frames, frames[1:])]
    if tree:
        web_viewer_frame(driver, s_v=1.0)
        return {"s_v": s_vs if budgets is None else budgets, "drawn": drawn, "ms": ms, "level": levels,
                "frames": frames, "step": step, "jump": None, "ratio": None}
    first, _ = web_viewer_frame(driver, s_v=s_vs[0], static=True)
    last, _ = web_viewer_frame(driver, s_v=s_vs[-1], static=True)
    web_viewer_frame(driver, s_v=1.0, static=False)
    jump = change(first, last)
    return {"s_v": s_vs, "drawn": drawn, "ms": ms, "level": levels, "frames": frames, "step": step, "jump": jump,
            "ratio": jump / max(max(step), 1e-12)}
