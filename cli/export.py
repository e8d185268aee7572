"""``clod-export``: write an adapted CLoD-GS model in forms other renderers can use.

    clod-export ADAPTED.ply --images SCENE [--resolution R] -o OUTDIR
                [--s-v X | --budget K] [--ordered] [--prune] [--sh-max-drop-db D]

Writes OUTDIR/point_cloud_clod.ply (the extended .ply, INRIA layout + ``sigma_d``), with
``--s-v``/``--budget`` OUTDIR/baked_sv{X}.ply / baked_budget{K}.ply (standard INRIA .ply of the
Gaussians that setting renders from the scene's views), with ``--ordered`` OUTDIR/ordered.ply
(Gaussians sorted so every prefix is a level of detail) and always OUTDIR/export.json (sizes,
counts, PSNRs, pruning and SH results). ``--prune`` drops Gaussians no training view renders at
any s_v >= 1; ``--sh-max-drop-db D`` lowers the SH degree while the training-view PSNR at
s_v = 1 drops by at most D dB. Both apply to every file written. See :mod:`clod_adapter.export`.

Exit status: 0 done, 2 bad input (one line on stderr naming the file or flag, nothing written),
130 interrupted.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130

EXTENDED_NAME = "point_cloud_clod.ply"
ORDERED_NAME = "ordered.ply"
JSON_NAME = "export.json"
PREFIX_FRACTIONS = (1.0, 0.5, 0.25, 0.1)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="clod-export",
        description="Export an adapted CLoD-GS model: the extended .ply, a baked standard .ply for one "
                    "setting, an importance-ordered .ply for prefix renderers; optionally prune "
                    "never-rendered Gaussians and unneeded SH bands.",
    )
    p.add_argument("ply", nargs="?", help="adapted model .ply (with sigma_d; from clod-adapt)")
    p.add_argument("--images", metavar="SCENE", help="scene folder (COLMAP: images/, sparse/0)")
    p.add_argument("--resolution", type=int, default=1, choices=(1, 2, 4, 8),
                   help="use images_R/ when present, else downsample by R (default 1)")
    p.add_argument("-o", "--output", metavar="OUTDIR", help="output folder")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--s-v", type=float, default=None, metavar="X",
                   help="bake the Gaussians rendered at s_v = X (>= 1) from the scene's views")
    g.add_argument("--budget", default=None, metavar="K",
                   help="bake the Gaussians of a per-view budget: a count (integer > 1) or a fraction (<= 1)")
    p.add_argument("--ordered", action="store_true", help="write ordered.ply and score its prefixes")
    p.add_argument("--prune", action="store_true",
                   help="drop Gaussians no training view renders at any s_v >= 1")
    p.add_argument("--sh-max-drop-db", type=float, default=None, metavar="D",
                   help="drop SH bands while the training-view PSNR at s_v = 1 falls by <= D dB")
    p.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"))
    return p


def _fmt(x: float) -> str:
    return f"{x:g}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def bad(msg: str) -> int:
        print(f"clod-export: error: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT

    if not args.ply or not args.images or not args.output:
        return bad("give PLY, --images SCENE and -o OUTDIR")

    from clod_adapter.io.ply import PlyFormatError, read_ply
    from clod_adapter.io.scene import SceneError
    from clod_adapter.io.scenes import load_scene
    from clod_adapter.pipeline import InputError, pick_device

    ply, scene_root, out = Path(args.ply), Path(args.images), Path(args.output)
    try:
        if not ply.is_file():
            raise InputError(f"{ply}: no such file")
        if not scene_root.is_dir():
            raise InputError(f"{scene_root}: no such scene folder")
        if args.s_v is not None and not (math.isfinite(args.s_v) and args.s_v >= 1):
            raise InputError(f"--s-v must be a number >= 1, got {args.s_v}")
        budget = None
        if args.budget is not None:
            try:
                b = float(args.budget)
            except ValueError:
                raise InputError(f"--budget {args.budget!r}: not a number") from None
            if not (math.isfinite(b) and b > 0):
                raise InputError(f"--budget must be > 0 (a count or a fraction <= 1), got {args.budget}")
            if b > 1 and b != int(b):
                raise InputError(f"--budget {args.budget}: counts must be integers (fractions are <= 1)")
            budget = b if b <= 1 else int(b)
        if args.sh_max_drop_db is not None and not (math.isfinite(args.sh_max_drop_db) and args.sh_max_drop_db >= 0):
            raise InputError(f"--sh-max-drop-db must be >= 0, got {args.sh_max_drop_db}")
        baked_name = None
        if args.s_v is not None:
            baked_name = f"baked_sv{_fmt(args.s_v)}.ply"
        elif budget is not None:
            baked_name = f"baked_budget{_fmt(budget)}.ply"
        names = [EXTENDED_NAME, JSON_NAME] + ([ORDERED_NAME] if args.ordered else []) + ([baked_name] if baked_name else [])
        if out.exists() and not out.is_dir():
            raise InputError(f"{out}: exists and is not a directory")
        if out.resolve() == ply.resolve():
            raise InputError(f"{out}: output path equals the input {ply}; -o takes a folder")
        for n in names:
            if (out / n).resolve() == ply.resolve():
                raise InputError(f"{out / n}: output path equals the input {ply}; choose another -o")
        dev = pick_device(args.device)
        model = read_ply(ply)
        if len(model) == 0:
            raise InputError(f"{ply}: the model has no Gaussians")
        if model.sigma_d is None:
            raise InputError(f"{ply}: no sigma_d property; not an adapted model (run clod-adapt first)")
        scene = load_scene(scene_root, resolution=args.resolution)
        if not scene.train:
            raise InputError(f"{scene_root}: no training views")
        train_imgs = [scene.load_image(c) for c in scene.train]
        test_cams = scene.test or scene.train[:1]
        test_imgs = [scene.load_image(c) for c in test_cams]
        anc = next((p for p in (out, *out.parents) if p.exists()), None)
        if anc is None or not os.access(anc, os.W_OK | os.X_OK):
            raise InputError(f"{out}: cannot create or write the output directory")
        report = export(model.to(dev), scene, train_imgs, test_cams, test_imgs, out, ply=ply,
                        s_v=args.s_v, budget=budget, baked_name=baked_name, ordered=args.ordered,
                        prune=args.prune, sh_max_drop_db=args.sh_max_drop_db, argv=argv)
        print(summary(report))
        print(f"clod-export: wrote {', '.join(report['files'])} to {out}")
    except (InputError, PlyFormatError, SceneError) as e:
        return bad(" ".join(str(e).split("\n")))
    except OSError as e:
        return bad(f"{e.filename if e.filename is not None else 'clod-export'}: {e.strerror or e}")
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    return 0


def export(model, scene, train_imgs, test_cams, test_imgs, out: Path, *, ply: Path, s_v, budget,
           baked_name, ordered, prune, sh_max_drop_db, argv=None) -> dict:
    """Compute everything, then write the files (each atomically); returns the export.json dict."""
    import torch

    from clod_adapter import export as ex
    from clod_adapter.io.atomic import atomic_write
    from clod_adapter.io.ply import write_ply
    from clod_adapter.report import bytes_per_gaussian

    t0 = time.perf_counter()
    n_in = len(model)
    rep: dict = {"input": str(ply), "scene": str(scene.root), "gaussians_in": n_in,
                 "sh_degree_in": model.sh_degree,
                 "train_views": len(scene.train), "test_views": [c.name for c in test_cams],
                 "resolution": [test_cams[0].width, test_cams[0].height]}
    with torch.no_grad():
        rep["psnr_test_sv1_in"] = _mean_psnr(ex, model, test_cams, test_imgs)
        if prune:
            model, n_drop = ex.prune_never_rendered(model, scene.train, anchor_cameras=scene.cameras)
            rep["prune"] = {"dropped": n_drop, "kept": len(model),
                            "bytes_saved": n_drop * bytes_per_gaussian(model),
                            "psnr_test_sv1_after": _mean_psnr(ex, model, test_cams, test_imgs)}
        if sh_max_drop_db is not None:
            model, info = ex.reduce_sh(model, scene.train, train_imgs, sh_max_drop_db)
            info["psnr_test_sv1_after"] = _mean_psnr(ex, model, test_cams, test_imgs)
            rep["sh"] = info
        rep["gaussians_out"] = len(model)
        rep["sh_degree_out"] = model.sh_degree
        baked = None
        if baked_name is not None:
            baked, binfo = ex.bake(model, scene.cameras, s_v=s_v, budget=budget, return_info=True)
            lod_ps = [ex.capped_psnr(ex.render_lod(model, c, s_v, budget=budget, estimator="paper").image, gt)
                      for c, gt in zip(test_cams, test_imgs)]
            bk_ps = [ex.capped_psnr(ex.render_lod(baked, c).image, gt) for c, gt in zip(test_cams, test_imgs)]
            rep["baked"] = {"file": baked_name, "s_v": s_v, "budget": budget, "cameras": "train+test",
                            "gaussians": len(baked), "mean_rendered_per_view_lod": binfo.per_view_rendered,
                            "opacity": binfo.chosen, "psnr_vs_render_lod_all_views": binfo.psnr_vs_lod,
                            "psnr_test_render_lod": sum(lod_ps) / len(lod_ps),
                            "psnr_test_baked": sum(bk_ps) / len(bk_ps)}
        ordered_model = None
        if ordered:
            persist = ex.persistence(model, scene.train)
            perm = ex.importance_order(model, scene.train, persist=persist)
            ordered_model = model.subset(perm)
            rep["ordered"] = {"file": ORDERED_NAME, "order_views": "train", "persistence_zero": int((persist == 0).sum()),
                              "prefix_vs_selection_test": ex.prefix_vs_selection(model, perm, test_cams, test_imgs,
                                                                                 PREFIX_FRACTIONS)}
    out.mkdir(parents=True, exist_ok=True)
    files = [EXTENDED_NAME]
    write_ply(out / EXTENDED_NAME, model)
    if baked is not None:
        write_ply(out / baked_name, baked)
        files.append(baked_name)
    if ordered_model is not None:
        write_ply(out / ORDERED_NAME, ordered_model)
        files.append(ORDERED_NAME)
    rep["bytes"] = {"input": ply.stat().st_size, **{f: (out / f).stat().st_size for f in files}}
    rep["seconds"] = round(time.perf_counter() - t0, 2)
    rep["command"] = "clod-export " + " ".join(sys.argv[1:] if argv is None else argv)
    files.append(JSON_NAME)
    rep["files"] = files
    with atomic_write(out / JSON_NAME, "w") as f:
        json.dump(rep, f, indent=2)
        f.write("\n")
    return rep


def _mean_psnr(ex, model, cams, imgs) -> float:
    ps = [ex.capped_psnr(ex.render_lod(model, c, 1.0, estimator="paper").image, gt) for c, gt in zip(cams, imgs)]
    return sum(ps) / len(ps)


def summary(rep: dict) -> str:
    lines = [f"{rep['gaussians_in']} -> {rep['gaussians_out']} Gaussians, SH {rep['sh_degree_in']} -> "
             f"{rep['sh_degree_out']}; test PSNR at s_v = 1: {rep['psnr_test_sv1_in']:.2f} dB in"]
    if "prune" in rep:
        p = rep["prune"]
        lines.append(f"prune: dropped {p['dropped']} ({p['bytes_saved']} bytes), test PSNR s_v=1 {p['psnr_test_sv1_after']:.2f} dB")
    if "sh" in rep:
        s = rep["sh"]
        lines.append(f"SH: degree {s['degree_in']} -> {s['degree_out']}, {s['bytes_saved']} bytes saved, "
                     f"train PSNR cost {s['psnr_cost_db']:.3f} dB")
    if "baked" in rep:
        b = rep["baked"]
        lines.append(f"baked: {b['gaussians']} Gaussians, opacity {b['opacity']}, test PSNR {b['psnr_test_baked']:.2f} "
                     f"(render_lod {b['psnr_test_render_lod']:.2f})")
    if "ordered" in rep:
        for r in rep["ordered"]["prefix_vs_selection_test"]:
            lines.append(f"prefix {r['fraction']:.0%} ({r['count']}): {r['psnr_prefix']:.2f} dB vs selection "
                         f"{r['psnr_selection']:.2f} dB ({r['rendered_per_view']:.0f} per view)")
    return "\n".join("clod-export: " + s for s in lines)


if __name__ == "__main__":
    sys.exit(main())
