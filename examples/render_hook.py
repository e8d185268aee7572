"""Render an adapted CLoD-GS model through the gsplat-style hook ``clod_rasterization``.

    python examples/render_hook.py [PLY] [--scene SCENE] [--out hook_demo.png]
    python examples/render_hook.py --synthetic          # no files needed

PLY defaults to ``runs/fern/point_cloud.ply`` when it exists (the output of ``clod-adapt``, which
carries ``sigma_d``); otherwise (or with ``--synthetic``) a small synthetic model is built with
``clod_adapter.io.synthetic`` and given a made-up ``sigma_d``. The camera is the first test view of
``--scene`` (COLMAP or NeRF-synthetic folder) when given, else the synthetic camera grid's centre
view, else a camera looking at the model's median from its -z side. One camera is rendered at
s_v = 1, 2, 4, at a budget of a quarter of the Gaussians at s_v = 1 and, for a model with a parent
tier, at twice its ``tier_s_v`` (the parents drawn); the images are written side by side to ``--out``, each captioned below with its setting and the Gaussians drawn
(the scene's own resolution unless ``--resolution R`` downsamples it).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from clod_adapter import clod_kwargs, clod_rasterization  # noqa: E402

DEFAULT_PLY = REPO / "runs" / "fern" / "point_cloud.ply"


def _synthetic(n: int, width: int, height: int):
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth

    gt = make_ground_truth(n, seed=0)
    g = torch.Generator().manual_seed(0)
    model = gt.with_sigma_d(0.2 + 0.6 * torch.rand(len(gt), generator=g))
    cams = make_cameras(3, 3, width=width, height=height)
    return model, cams[4]


def _look_at_model(model, width: int, height: int):
    from clod_adapter.io.scene import Camera
    from clod_adapter.io.synthetic import look_at

    m = model.means.detach().double()
    target = m.median(dim=0).values
    spread = (m.quantile(0.9, dim=0) - m.quantile(0.1, dim=0)).norm()
    center = target - torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64) * spread
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera(name="view", image_path=Path("view"), viewmat=look_at(center, target).float(),
                  K=K, width=width, height=height)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("ply", nargs="?", help=f"adapted .ply (default {DEFAULT_PLY} if present)")
    p.add_argument("--scene", help="scene folder for the camera (COLMAP or NeRF-synthetic)")
    p.add_argument("--resolution", type=int, default=1, choices=(1, 2, 4, 8),
                   help="--scene downsampling: images_R/ or the images / R (default 1: the scene's size)")
    p.add_argument("--synthetic", action="store_true", help="use the synthetic model even if PLY exists")
    p.add_argument("--n", type=int, default=3000, help="synthetic model size (default 3000)")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--out", default="hook_demo.png", help="PNG to write (default hook_demo.png)")
    args = p.parse_args(argv)

    ply = None if args.synthetic else Path(args.ply) if args.ply else DEFAULT_PLY if DEFAULT_PLY.is_file() else None
    if ply is None:
        model, cam = _synthetic(args.n, args.width, args.height)
        print(f"synthetic model: {len(model)} Gaussians")
    else:
        from clod_adapter.io.ply import read_ply

        model = read_ply(ply)
        if model.sigma_d is None:
            print(f"{ply}: no sigma_d (not adapted by clod-adapt)", file=sys.stderr)
            return 2
        print(f"{ply}: {len(model)} Gaussians")
        cam = None
    if args.scene:
        from clod_adapter.io.load import load_scene

        scene = load_scene(args.scene, resolution=args.resolution)
        cam = (scene.test or scene.train)[0]
    elif cam is None:
        cam = _look_at_model(model, args.width, args.height)

    with torch.no_grad():
        base = (model.means, model.quats, model.scales, model.opacities, model.colors,
                cam.viewmat[None], cam.K[None], cam.width, cam.height)
        kw = dict(sh_degree=model.sh_degree, **clod_kwargs(model), backend="cpu")
        clod_rasterization(*base, **kw, s_v=1.0)  # warm-up (builds / loads the CPU compositor)
        tiles, caps, n1 = [], [], None
        levels = [("s_v=1", {"s_v": 1.0}), ("s_v=2", {"s_v": 2.0}), ("s_v=4", {"s_v": 4.0}), ("budget", None)]
        tier_s_v = model.lod.tier_s_v if model.lod is not None and model.parents is not None else 0.0
        if tier_s_v > 0:  # past the switch: the parent tier (docs/method.md "Merged tiers")
            levels.append((f"s_v={2 * tier_s_v:g}", {"s_v": 2 * tier_s_v}))
        for label, extra in levels:
            if extra is None:
                extra = {"budget": max(1, n1 // 4)}
                label = f"budget={extra['budget']}"
            t0 = time.perf_counter()
            col, _, meta = clod_rasterization(*base, **kw, **extra)
            ms = (time.perf_counter() - t0) * 1e3
            n, n_par = meta["lod_n_rendered"][0], meta["lod_n_parents"][0]
            n1 = n if n1 is None else n1
            par = f" ({n_par:,} of them parents)" if n_par else ""
            print(f"{label:>12}: {n:8d} Gaussians rendered{par} (s_v {meta['lod_s_v'][0]:.3f}), {ms:8.1f} ms")
            tiles.append(col[0])
            caps.append(f"{label}\n{n:,} Gaussians")
    from clod_adapter.export.figures import label_panels

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet = label_panels(tiles, caps)
    sheet.save(out)
    print(f"wrote {out} ({sheet.width}x{sheet.height})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
