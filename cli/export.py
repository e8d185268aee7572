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

import json
import math
import sys
import time
from pathlib import Path

from clod_adapter import jobs
from clod_adapter.jobs import EXIT_BAD_INPUT, EXIT_INTERRUPTED, InputError, check_flag  # noqa: F401

EXTENDED_NAME = "point_cloud_clod.ply"
ORDERED_NAME = "ordered.ply"
JSON_NAME = "export.json"
PREFIX_FRACTIONS = (1.0, 0.5, 0.25, 0.1)
EXAMPLE = ("clod-export runs/fern -s ../shared/data/fern --resolution 2 -o runs/fern_export --s-v 2 "
           "--ordered --prune")


def build_parser():
    p = jobs.make_parser(
        "clod-export",
        "Export an adapted CLoD-GS model: the extended .ply, a baked standard .ply for one setting, an "
        "importance-ordered .ply for prefix renderers; optionally prune never-rendered Gaussians and "
        "unneeded SH bands.", EXAMPLE)
    p.add_argument("ply", nargs="?", metavar="ADAPTED",
                   help="adapted model (with sigma_d): a clod-adapt output folder or its point_cloud.ply")
    p.add_argument("--images", "-s", "--source_path", "--source-path", dest="images", metavar="SCENE",
                   help="scene folder: COLMAP (images/, sparse/0) or NeRF-synthetic (transforms_*.json)")
    p.add_argument("-r", "--resolution", type=int, default=1, choices=(1, 2, 4, 8),
                   help="use images_R/ when present, else downsample by R (default 1)")
    p.add_argument("-o", "--output", metavar="OUTDIR", help="output folder, new or empty")
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
    p.add_argument("--spz", action="store_true",
                   help="also write each exported model as .spz (Niantic's compressed format, read by Spark, "
                        "SuperSplat, Scaniverse; no sigma_d: a plain model) through gsply "
                        "(pip install -e \".[spz]\")")
    jobs.add_common_flags(p, device_default="cpu")
    return p


def _fmt(x: float) -> str:
    return f"{x:g}"


def main(argv: list[str] | None = None) -> int:
    jobs.thread_defaults()  # before torch is imported
    args = build_parser().parse_args(argv)
    return jobs.run_cli("clod-export", lambda: _main(args, argv))


def _main(args, argv) -> int:
    if not args.ply or not args.images or not args.output:
        raise InputError("give ADAPTED, --images SCENE and -o OUTDIR")
    ply, scene_root, out = Path(args.ply), Path(args.images), Path(args.output)
    if args.s_v is not None:
        check_flag(math.isfinite(args.s_v) and args.s_v >= 1, "--s-v", "a number >= 1", args.s_v)
    budget = None
    if args.budget is not None:
        budget = jobs.parse_budget(args.budget, "--budget")
        if budget == 0:
            raise InputError(f"--budget must be > 0 (a count or a fraction <= 1), got {args.budget}")
    if args.sh_max_drop_db is not None:
        check_flag(math.isfinite(args.sh_max_drop_db) and args.sh_max_drop_db >= 0, "--sh-max-drop-db", ">= 0",
                   args.sh_max_drop_db)
    if args.threads is not None:
        check_flag(args.threads >= 1, "--threads", ">= 1", args.threads)
    if not ply.exists():
        raise InputError(f"{ply}: no such file")
    if not scene_root.is_dir():
        raise InputError(f"{scene_root}: no such scene folder")
    if args.spz:
        try:
            import gsply  # noqa: F401
        except ImportError:
            raise InputError("--spz: needs the gsply package (pip install -e \".[spz]\")") from None
    jobs.set_threads(args.threads)

    from clod_adapter.io.load import resolve_model_path
    from clod_adapter.io.ply import read_ply
    from clod_adapter.io.scene import load_scene

    ply = resolve_model_path(ply, prefer="point_cloud.ply")
    baked_name = None
    if args.s_v is not None:
        baked_name = f"baked_sv{_fmt(args.s_v)}.ply"
    elif budget is not None:
        baked_name = f"baked_budget{_fmt(budget)}.ply"
    names = [EXTENDED_NAME, JSON_NAME] + ([ORDERED_NAME] if args.ordered else []) + ([baked_name] if baked_name else [])
    if args.spz:
        names += [Path(n).with_suffix(".spz").name for n in names if n.endswith(".ply")]
    jobs.check_output_dir(out, [ply], names, create=False, force=args.force)
    dev = jobs.pick_device(args.device)
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
    report = export(model.to(dev), scene, train_imgs, test_cams, test_imgs, out, ply=ply,
                    s_v=args.s_v, budget=budget, baked_name=baked_name, ordered=args.ordered,
                    prune=args.prune, sh_max_drop_db=args.sh_max_drop_db, argv=argv, progress=not args.quiet,
                    spz=args.spz)
    print(summary(report))
    print(f"clod-export: wrote {', '.join(report['files'])} to {out} in {report['seconds']:.0f} s")
    return 0


def export(model, scene, train_imgs, test_cams, test_imgs, out: Path, *, ply: Path, s_v, budget,
           baked_name, ordered, prune, sh_max_drop_db, argv=None, progress: bool = False, spz: bool = False) -> dict:
    """Compute everything, then write the files (each atomically); returns the export.json dict.
    ``progress``: one step per phase (a tqdm bar on a terminal, else a line per phase)."""
    import torch

    from clod_adapter import export as ex
    from clod_adapter.io.atomic import atomic_write
    from clod_adapter.metrics import psnr
    from clod_adapter.io.ply import read_ply, write_ply
    from clod_adapter.report import bytes_per_gaussian

    t0 = time.perf_counter()
    phases = ["input PSNR"] + (["prune"] if prune else []) + (["SH bands"] if sh_max_drop_db is not None else []) \
        + (["bake"] if baked_name is not None else []) + (["order"] if ordered else []) + ["write"]
    bar = jobs.progress_bar(len(phases), "clod-export", unit="step", disable=not progress, every=1e-9)
    done = iter(phases)

    def step():
        bar.set_postfix_str(next(done))
        bar.update(1)

    n_in = len(model)
    rep: dict = {"input": str(ply), "scene": str(scene.root), "gaussians_in": n_in,
                 "sh_degree_in": model.sh_degree,
                 "train_views": len(scene.train), "test_views": [c.name for c in test_cams],
                 "resolution": [test_cams[0].width, test_cams[0].height]}
    with torch.no_grad():
        rep["psnr_test_sv1_in"] = _mean_psnr(ex, model, test_cams, test_imgs)
        step()
        if prune:
            model, n_drop = ex.prune_never_rendered(model, scene.train, anchor_cameras=scene.cameras)
            rep["prune"] = {"dropped": n_drop, "kept": len(model),
                            "bytes_saved": n_drop * bytes_per_gaussian(model),
                            "psnr_test_sv1_after": _mean_psnr(ex, model, test_cams, test_imgs)}
            step()
        if sh_max_drop_db is not None:
            model, info = ex.reduce_sh(model, scene.train, train_imgs, sh_max_drop_db)
            info["psnr_test_sv1_after"] = _mean_psnr(ex, model, test_cams, test_imgs)
            rep["sh"] = info
            step()
        rep["gaussians_out"] = len(model)
        rep["sh_degree_out"] = model.sh_degree
        baked = None
        if baked_name is not None:
            baked, binfo = ex.bake(model, scene.cameras, s_v=s_v, budget=budget, return_info=True)
            lod_ps = [psnr(ex.render_lod(model, c, s_v, budget=budget, estimator="paper").image, gt, cap=True)
                      for c, gt in zip(test_cams, test_imgs)]
            bk_ps = [psnr(ex.render_lod(baked, c).image, gt, cap=True) for c, gt in zip(test_cams, test_imgs)]
            rep["baked"] = {"file": baked_name, "s_v": s_v, "budget": budget, "cameras": "train+test",
                            "gaussians": len(baked), "mean_rendered_per_view_lod": binfo.per_view_rendered,
                            "opacity": binfo.chosen, "psnr_vs_render_lod_all_views": binfo.psnr_vs_lod,
                            "psnr_test_render_lod": sum(lod_ps) / len(lod_ps),
                            "psnr_test_baked": sum(bk_ps) / len(bk_ps)}
            step()
        ordered_model = None
        if ordered:
            persist = ex.persistence(model, scene.train)
            perm = ex.importance_order(model, scene.train, persist=persist)
            ordered_model = model.subset(perm)
            rep["ordered"] = {"file": ORDERED_NAME, "order_views": "train", "persistence_zero": int((persist == 0).sum()),
                              "prefix_vs_selection_test": ex.prefix_vs_selection(model, perm, test_cams, test_imgs,
                                                                                 PREFIX_FRACTIONS)}
            step()
    jobs.check_output_dir(out, [ply], force=True)  # checked before; create it now
    files = [EXTENDED_NAME]
    write_ply(out / EXTENDED_NAME, model)
    if baked is not None:
        write_ply(out / baked_name, baked)
        files.append(baked_name)
    if ordered_model is not None:
        write_ply(out / ORDERED_NAME, ordered_model)
        files.append(ORDERED_NAME)
    if spz:
        for f in list(files):
            files.append(write_spz(out / Path(f).with_suffix(".spz").name, read_ply(out / f)))
    rep["bytes"] = {"input": ply.stat().st_size, **{f: (out / f).stat().st_size for f in files}}
    rep["seconds"] = round(time.perf_counter() - t0, 2)
    rep["command"] = "clod-export " + " ".join(sys.argv[1:] if argv is None else argv)
    files.append(JSON_NAME)
    rep["files"] = files
    with atomic_write(out / JSON_NAME, "w") as f:
        json.dump(rep, f, indent=2)
        f.write("\n")
    step()
    bar.close()
    return rep


def write_spz(path: Path, model) -> str:
    """Write ``model`` (``sigma_d`` dropped: SPZ has no extra attributes) as .spz with gsply
    (``gsply.write_spz``, SPZ version 3, 12 fractional bits), atomically; returns the file name.

    The plain INRIA .ply goes through ``gsply.plyread`` so gsply's own conventions (log scales,
    logit opacities) are used."""
    import os
    import tempfile

    import gsply

    from clod_adapter.io.ply import write_ply

    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".spz-") as d:
        plain = write_ply(Path(d) / "plain.ply", model.with_sigma_d(None))
        tmp = Path(d) / path.name
        gsply.write_spz(tmp, gsply.plyread(plain))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    return path.name


def _mean_psnr(ex, model, cams, imgs) -> float:
    from clod_adapter.metrics import psnr

    ps = [psnr(ex.render_lod(model, c, 1.0, estimator="paper").image, gt, cap=True) for c, gt in zip(cams, imgs)]
    return sum(ps) / len(ps)


def summary(rep: dict) -> str:
    lines = [f"{rep['gaussians_in']:,} -> {rep['gaussians_out']:,} Gaussians, SH degree {rep['sh_degree_in']} -> "
             f"{rep['sh_degree_out']}; test PSNR of the input at s_v = 1: {rep['psnr_test_sv1_in']:.2f} dB"]
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
