"""How far the viewer's picture (viser's WebGL splat renderer) is from our rasteriser's.

Starts the viewer on MODEL, opens it in headless chromium (software WebGL), puts the browser
camera on each test view of SCENE and, at each level, grabs the browser's frame
(``client.get_render``, lossless PNG) at that view's pose, size and vertical field of view. It
compares that frame with

* our rasteriser drawing *exactly the Gaussians the viewer sent* (same selection, opacities
  and SH colours): the renderer difference alone (PSNR over the whole frame and over the pixels
  either covers, mean absolute difference);
* the photo, next to our own ``render_lod`` of the same view and level against the photo.

    python -m benchmarks.studies.viewer_vs_rasteriser ../shared/data/fern/pretrained/point_cloud/iteration_7000/point_cloud.ply \\
        --images ../shared/data/fern --resolution 2

(an adapted model gets one row per ``--sv`` level). Needs chromium + chromium-driver and the
``test`` extra (viser, selenium); about 1 min for fern on 2 cores.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

from clod_adapter.io.load import load_scene  # noqa: E402
from clod_adapter.lod.draw import render_lod  # noqa: E402
from clod_adapter.metrics import psnr  # noqa: E402
from clod_adapter.render import rasterization  # noqa: E402
from clod_adapter.viewer import camera_from_pose, load_view_model, model_max_sv  # noqa: E402
from clod_adapter.viewer.app import LodViewer, apply_pose, scene_camera_list  # noqa: E402
from clod_adapter.viewer.cameras import scene_start_view  # noqa: E402
from tests.browser import (browser_missing, chromium_driver, compare_frames,  # noqa: E402
                     fit_canvas_aspect, stable_render)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--images", required=True)
    ap.add_argument("--resolution", type=int, default=2)
    ap.add_argument("--sv", default="1,2,5", help="levels for a model with sigma_d (comma list)")
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--save", metavar="DIR", help="write viser | ours (same Gaussians) | photo strips here")
    args = ap.parse_args()
    why = browser_missing()
    if why:
        sys.exit(f"viewer_vs_rasteriser: {why}")
    torch.set_num_threads(2)
    model = load_view_model(args.model)
    scene = load_scene(args.images, resolution=args.resolution)
    lod = model.sigma_d is not None
    levels = [float(s) for s in args.sv.split(",")] if lod else [None]
    app = LodViewer(model, max_sv=model_max_sv(args.model), scene_cameras=scene_camera_list(scene),
                    calibrate=False)
    port = app.start(host="127.0.0.1", port=0)
    t_start = time.perf_counter()
    driver = chromium_driver(tempfile.mkdtemp(prefix="clod-view-bench-"), (900, 700))
    rows = []
    try:
        driver.get(f"http://127.0.0.1:{port}/")
        deadline = time.monotonic() + args.timeout
        while not app.sessions():
            if time.monotonic() > deadline:
                sys.exit("viewer_vs_rasteriser: the browser did not connect")
            time.sleep(0.2)
        session = next(iter(app.sessions().values()))
        client = session.client
        c0 = scene.test[0]
        canvas = fit_canvas_aspect(driver, c0.width, c0.height)  # the selection is made for the view
        print(f"{len(model):,} Gaussians; canvas {canvas[0]}x{canvas[1]} CSS px; frames {c0.width}x{c0.height}")
        for cam in scene.test:
            pose = scene_start_view(cam, model)
            apply_pose(client.camera, pose, client)
            for sv in levels:
                if sv is not None:
                    session.sv.value = sv
                    session.dirty.set()
                rec = app.wait_for_view(
                    lambda r: np.allclose(r.camera.center.numpy(), pose.position, atol=1e-4)
                    and r.settings.get("s_v") == sv, timeout=args.timeout)
                frame = stable_render(client, cam.height, cam.width, timeout=args.timeout,
                                      wxyz=pose.wxyz, position=pose.position, fov=pose.fov)
                ref = camera_from_pose(pose.wxyz, pose.position, pose.fov, cam.width, cam.height)
                p = rec.payload
                idx = p.indices
                col, _, _ = rasterization(model.means[idx], model.quats[idx], model.scales[idx],
                                          torch.from_numpy(p.opacities[:, 0]),
                                          torch.from_numpy(np.clip(p.rgbs, 0, 1)), ref.viewmat[None],
                                          ref.K[None], cam.width, cam.height,
                                          backgrounds=torch.zeros(1, 3), backend="cpu")
                same = col[0].clamp(0, 1).numpy()
                d = compare_frames(same, frame)
                gt = scene.load_image(cam)
                ours = render_lod(model, cam, s_v=sv, background=(0.0, 0.0, 0.0)).image.clamp(0, 1)
                if args.save:
                    from PIL import Image

                    Path(args.save).mkdir(parents=True, exist_ok=True)
                    strip = np.concatenate([frame, same, gt.numpy()], axis=1)
                    tag = "" if sv is None else f"_sv{sv:g}"
                    Image.fromarray((strip * 255 + 0.5).astype(np.uint8)).save(
                        Path(args.save) / f"{Path(cam.name).stem}{tag}.png")
                rows.append((cam.name, sv, p.n_drawn, d["psnr"], d["psnr_covered"], d["mad"],
                             float(psnr(torch.from_numpy(frame), gt)), float(psnr(ours, gt))))
    finally:
        driver.quit()
        app.stop()
    print("\n| view | s_v | Gaussians sent | PSNR viser vs ours | PSNR covered px | mean abs diff "
          "| PSNR viser vs photo | PSNR ours vs photo |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, sv, n, ps, pc, mad, pv, po in rows:
        svs = "-" if sv is None else f"{sv:g}"
        print(f"| {name} | {svs} | {n:,} | {ps:.2f} | {pc:.2f} | {mad:.4f} | {pv:.2f} | {po:.2f} |")
    arr = np.array([r[3:] for r in rows], dtype=np.float64)
    print(f"\nmean over {len(rows)} frames: viser vs ours {arr[:, 0].mean():.2f} dB (covered {arr[:, 1].mean():.2f} dB, "
          f"mad {arr[:, 2].mean():.4f}); vs photo: viser {arr[:, 3].mean():.2f} dB, ours {arr[:, 4].mean():.2f} dB; "
          f"{time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
