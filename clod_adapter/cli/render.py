"""``clod-render``: test-view images at one level of detail, and an MP4 while s_v sweeps.

    clod-render ADAPTED --images SCENE [--resolution R] [--s-v X | --budget K] [--views test|train|all]
                [--path cameras|orbit] [--frames 90] [--fps 30] [--no-video] -o OUTDIR

Writes OUTDIR/views/<image>.png (each view at the level, default s_v = 1), OUTDIR/lod_<path>.mp4
(unless ``--no-video``: ``--frames`` frames along the scene's cameras or an orbit, s_v going from
1 to the trained maximum and back, or fixed by ``--s-v``/``--budget``; each frame captioned with s_v
and the Gaussians drawn) and OUTDIR/render.json. The MP4 needs the ``[video]`` extra (imageio and
the imageio-ffmpeg binary wheel).

Exit status: 0 done, 2 bad input (one line on stderr, nothing written), 130 interrupted.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

from clod_adapter import jobs
from clod_adapter.cli import common
from clod_adapter.cli.common import check_flag
from clod_adapter.errors import InputError

EXAMPLE = "clod-render runs/fern -s ../shared/data/fern --resolution 2 --path orbit -o runs/fern_render"
JSON_NAME = "render.json"


def build_parser():
    p = common.make_parser(
        "clod-render",
        "Render an adapted CLoD-GS model: the test views at one level of detail (PNG) and a short MP4 "
        "along the scene's cameras or an orbit while s_v sweeps.", EXAMPLE)
    common.add_adapted_inputs(p)
    p.add_argument("-o", "--output", metavar="OUTDIR", help="output folder, new or empty (default ./clod_render)")
    common.add_level_flags(p, "level of detail (>= 1) of the images, and of the video instead of a sweep (default 1)",
                         "render at most K Gaussians per view (an integer count > 1 or a fraction <= 1) instead")
    p.add_argument("--views", default="test", choices=("test", "train", "all"),
                   help="which views to render as images (default test: every 8th image)")
    p.add_argument("--path", default="cameras", choices=("cameras", "orbit"),
                   help="video camera path: through the scene's cameras sorted by name, or an orbit around "
                        "their centroid looking at the scene (forward-facing scenes) (default cameras)")
    p.add_argument("--frames", type=int, default=90, help="video frames (default 90)")
    p.add_argument("--fps", type=int, default=30, help="video frames per second (default 30)")
    p.add_argument("--max-sv", type=float, default=None,
                   help="top of the video's s_v sweep (default: the trained maximum from the model's "
                        "header, else adapt_state.safetensors beside it, else 5; a model with a parent tier: "
                        "where its parents reach that maximum, swept in ln s_v)")
    p.add_argument("--no-video", action="store_true", help="only the images")
    p.add_argument("--background", default="black", choices=("black", "white"),
                   help="colour behind the scene (NeRF-synthetic RGBA images are composited over it)")
    common.add_common_flags(p)
    return p


def main(argv: list[str] | None = None) -> int:
    common.thread_defaults()  # before torch is imported
    args = build_parser().parse_args(argv)
    return common.run_cli("clod-render", lambda: _main(args))


def _check_flags(args):
    """The flags' values; returns the budget (None, or a ``Budget`` of a count or a share)."""
    if not args.ply or not args.images:
        raise InputError("give ADAPTED and --images SCENE")
    if args.s_v is not None:
        check_flag(math.isfinite(args.s_v) and args.s_v >= 1, "--s-v", "a number >= 1", args.s_v)
    budget = None
    if args.budget is not None:
        from clod_adapter.lod.budget import as_budget

        budget = as_budget(common.parse_budget(args.budget, "--budget"))
    check_flag(args.frames >= 2, "--frames", ">= 2", args.frames)
    check_flag(args.fps >= 1, "--fps", ">= 1", args.fps)
    if args.max_sv is not None:
        check_flag(args.max_sv >= 1, "--max-sv", ">= 1", args.max_sv)
    return budget


def _render_views(model, scene, cams, level: dict, bg, out: Path, bar) -> list:
    """Each scene view at the level: its PNG in ``out/views`` (atomically) and its record."""
    import numpy as np
    from PIL import Image

    from clod_adapter.io.atomic import atomic_save
    from clod_adapter.metrics import psnr
    from clod_adapter.lod.draw import render_lod

    views = []
    for c in cams:
        r = render_lod(model, c, level["s_v"], budget=level["budget"], background=bg)
        img = r.image.clamp(0, 1)
        gt = scene.load_image(c).to(img.device)
        views.append({"view": c.name, "psnr": psnr(img, gt), "gaussians": r.n_rendered, "s_v": r.s_v})
        arr = (img.cpu().numpy() * 255 + 0.5).astype(np.uint8)
        atomic_save(out / "views" / f"{Path(c.name).stem}.png",
                    lambda tmp, arr=arr: Image.fromarray(arr).save(tmp, format="PNG"))
        bar.update(1)
    return views


def _render_video(model, scene, args, level: dict, max_sv: float, bg, path: Path, bar) -> dict:
    """The MP4 along the camera path (1 -> max_sv -> 1, or the fixed level; a model with a parent
    tier, without ``--max-sv``: 1 -> ``max_sv`` times :func:`clod_adapter.lod.draw.tier_reach` -> 1, even in ``ln s_v``), each
    frame captioned with its s_v and count; returns its record."""
    import numpy as np

    from clod_adapter.export.figures import label_panels
    from clod_adapter.export.video import camera_path, orbit_path, write_mp4
    from clod_adapter.lod.draw import render_lod, tier_reach

    n_frames, n = args.frames, len(model)
    cams = camera_path(scene.cameras, n_frames) if args.path == "cameras" else \
        orbit_path(scene.cameras, model.means, n_frames)
    st = model.lod
    if args.s_v is None and level["budget"] is None and model.parents is not None and st.tier_s_v > 0 \
            and args.max_sv is None:  # parent tiers: 1 -> where the last one reaches its max_sv -> 1, in ln s_v
        top = max_sv * tier_reach(model)
        svs = [top ** (0.5 * (1 - math.cos(2 * math.pi * i / n_frames))) for i in range(n_frames)]
    elif args.s_v is None and level["budget"] is None:  # 1 -> max_sv -> 1
        svs = [1.0 + (max_sv - 1.0) * 0.5 * (1 - math.cos(2 * math.pi * i / n_frames)) for i in range(n_frames)]
    else:
        svs = [args.s_v] * n_frames
    frames, counts = [], []
    for cam, s in zip(cams, svs):
        r = render_lod(model, cam, s, budget=level["budget"], background=bg)
        cap = (f"s_v = {r.s_v:.2f}   " if r.s_v is not None else "") + \
            f"{r.n_rendered:,} Gaussians ({100 * r.n_rendered / n:.0f} %)"
        frames.append(np.asarray(label_panels([r.image], [cap], min_width=480)))
        counts.append(r.n_rendered)
        bar.update(1)
    write_mp4(path, frames, fps=args.fps)
    return {"file": path.name, "path": args.path, "frames": n_frames, "fps": args.fps,
            "s_v": svs, "gaussians": counts, "size": [int(frames[0].shape[1]), int(frames[0].shape[0])]}


def _main(args) -> int:
    budget = _check_flags(args)
    ply, scene_root = Path(args.ply), Path(args.images)
    out = Path(args.output or "clod_render")
    if not ply.exists():
        raise InputError(f"{ply}: no such file")
    if not scene_root.is_dir():
        raise InputError(f"{scene_root}: no such scene folder")
    from clod_adapter.export.video import video_available

    if not args.no_video:
        why = video_available()
        if why:
            raise InputError(f"the MP4 {why} (or pass --no-video)")
    common.set_threads(args.threads)

    import torch

    from clod_adapter.train.state import max_sv_from_state
    from clod_adapter.io.atomic import atomic_write
    from clod_adapter.io.load import load_scene, resolve_model_path
    from clod_adapter.io.ply import read_ply

    t0 = time.perf_counter()
    ply = resolve_model_path(ply, prefer="point_cloud.ply")
    video_name = f"lod_{args.path}.mp4"
    jobs.check_output_dir(out, [ply], [JSON_NAME, video_name, "views"], create=False, force=args.force)
    dev = jobs.pick_device(args.device)
    model = read_ply(ply)
    if len(model) == 0:
        raise InputError(f"{ply}: the model has no Gaussians")
    if model.sigma_d is None:
        raise InputError(f"{ply}: no sigma_d property; not an adapted model (run clod-adapt first)")
    bg = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
    scene = load_scene(scene_root, resolution=args.resolution, background=bg)
    cams = {"test": scene.test or scene.train[:1], "train": scene.train, "all": scene.cameras}[args.views]
    if not cams:
        raise InputError(f"{scene_root}: the scene has no views")
    max_sv = args.max_sv if args.max_sv is not None else \
        (model.lod.max_sv if model.lod is not None else (max_sv_from_state(ply) or 5.0))
    model = model.to(dev)
    level = {"s_v": args.s_v if args.s_v is not None else (None if budget is not None else 1.0), "budget": budget}
    jobs.check_output_dir(out, [ply], force=True)
    (out / "views").mkdir(exist_ok=True)
    n_frames = 0 if args.no_video else args.frames
    bar = jobs.progress_bar(len(cams) + n_frames, "clod-render", unit="frame", disable=args.quiet)
    with torch.no_grad():
        views = _render_views(model, scene, cams, level, bg, out, bar)
        video = _render_video(model, scene, args, level, max_sv, bg, out / video_name, bar) if n_frames else None
    bar.close()
    rep = {"model": str(ply), "scene": str(scene_root), "resolution": args.resolution, "level": level,
           "max_sv": max_sv, "views": views, "video": video, "seconds": round(time.perf_counter() - t0, 1)}
    with atomic_write(out / JSON_NAME, "w") as f:
        json.dump(rep, f, indent=1)
    mean = sum(v["psnr"] for v in views) / len(views)
    what = f"s_v = {level['s_v']:g}" if level["s_v"] is not None else f"budget {budget.amount:g}"
    print(f"clod-render: {len(views)} {args.views} views at {what}: mean PSNR {mean:.2f} dB, "
          f"{sum(v['gaussians'] for v in views) / len(views):,.0f} Gaussians per view")
    print(f"clod-render: wrote views/ ({len(views)} PNG)" + (f", {video_name} ({n_frames} frames)" if video else "")
          + f", {JSON_NAME} to {out} in {rep['seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
