"""``clod-export``: write an adapted CLoD-GS model in forms other renderers can use.

    clod-export ADAPTED.ply --images SCENE [--resolution R] -o OUTDIR
                [--s-v X | --budget K] [--ordered] [--lod-meta [DIR]] [--web [DIR]] [--prune]
                [--sh-max-drop-db D]

Writes OUTDIR/point_cloud_clod.ply (the extended .ply, INRIA layout + ``sigma_d``), with
``--s-v``/``--budget`` OUTDIR/baked_sv{X}.ply / baked_budget{K}.ply (standard INRIA .ply of the
Gaussians that setting renders from the training views), with ``--ordered`` OUTDIR/ordered.ply
(Gaussians sorted so every prefix is a level of detail), with ``--lod-meta`` a streamed-SOG LoD
set of the model's levels (``lod-meta.json`` + chunk folders, built by splat-transform 3.7.0;
into DIR, or OUTDIR), with ``--web`` a static page drawing the continuous LoD per frame on the
GPU with the vendored PlayCanvas engine (index.html, clod.mjs, clod_tree.mjs, the engine, model.ply,
clod.bin, clod.json; into DIR, or OUTDIR; serve it with ``python -m http.server``) and always
OUTDIR/export.json (sizes,
counts, PSNRs, pruning and SH results). ``--prune`` drops Gaussians no training view renders at
any s_v >= 1; ``--sh-max-drop-db D`` lowers the SH degree while the training-view PSNR at
s_v = 1 drops by at most D dB. Both apply to every file written. The job is
:func:`clod_adapter.jobs.export.export` (operations: :mod:`clod_adapter.export.bake`).

Exit status: 0 done, 2 bad input (one line on stderr naming the file or flag, nothing written),
130 interrupted.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

from clod_adapter import jobs
from clod_adapter.cli import common
from clod_adapter.cli.common import check_flag
from clod_adapter.errors import InputError

EXAMPLE = ("clod-export runs/fern -s ../shared/data/fern --resolution 2 -o runs/fern_export --s-v 2 "
           "--ordered --prune")


def build_parser():
    p = common.make_parser(
        "clod-export",
        "Export an adapted CLoD-GS model: the extended .ply, a baked standard .ply for one setting, an "
        "importance-ordered .ply for prefix renderers; optionally prune never-rendered Gaussians and "
        "unneeded SH bands.", EXAMPLE)
    common.add_adapted_inputs(p)
    p.add_argument("-o", "--output", metavar="OUTDIR", help="output folder, new or empty")
    common.add_level_flags(p, "bake the Gaussians rendered at s_v = X (>= 1) from the training views",
                         "bake the Gaussians of a per-view budget: a count (integer > 1) or a fraction (<= 1)")
    p.add_argument("--ordered", action="store_true", help="write ordered.ply and score its prefixes")
    p.add_argument("--lod-meta", nargs="?", const="", default=None, metavar="DIR",
                   help="write a streamed-SOG LoD set (lod-meta.json + chunks; PlayCanvas, SuperSplat, Babylon.js) "
                        "of the model's levels: with a merge tree, the model whole, then the tree's cut at each "
                        "node's reference distance with as many Gaussians as each merged tier; without one, baked "
                        "at s_v = 1, 1.59, 2.52, 4, ... (the share in view halving per level) up to max_sv; "
                        "through splat-transform (`npm ci`); into DIR, default OUTDIR")
    p.add_argument("--sog-sh-iterations", type=int, default=None, metavar="N",
                   help="k-means iterations of the LoD set's SH palette (splat-transform --sh-iterations; default "
                        "its 10). On the CPU this dominates: fewer iterations for large SH-3 models")
    p.add_argument("--web", nargs="?", const="", default=None, metavar="DIR",
                   help="write a static web page drawing the continuous LoD per frame on the GPU (PlayCanvas engine "
                        "vendored from npm by `npm ci`; a slider for s_v, a static-cut toggle, drawn count and "
                        "frame time; a merge tree's page: one cut per frame and a splat budget instead of the "
                        "toggle); into DIR, default OUTDIR; open it with `python -m http.server` in DIR")
    p.add_argument("--prune", action="store_true",
                   help="drop Gaussians no training view renders at any s_v >= 1")
    p.add_argument("--sh-max-drop-db", type=float, default=None, metavar="D",
                   help="drop SH bands while the training-view PSNR at s_v = 1 falls by <= D dB")
    p.add_argument("--spz", action="store_true",
                   help="also write each exported model as .spz (Niantic's compressed format, read by Spark, "
                        "SuperSplat, Scaniverse; no sigma_d: a plain model) through gsply "
                        "(pip install -e \".[spz]\")")
    common.add_common_flags(p, device_default="cpu")
    return p


def _fmt(x: float) -> str:
    return f"{x:g}"


def main(argv: list[str] | None = None) -> int:
    common.thread_defaults()  # before torch is imported
    args = build_parser().parse_args(argv)
    return common.run_cli("clod-export", lambda: _main(args, argv))


def _check_tools(spz: bool, lod_dir, web_dir) -> None:
    """The optional tools the asked outputs need: gsply (``--spz``), splat-transform
    (``--lod-meta``), the PlayCanvas engine (``--web``); a one-line error naming the flag."""
    if spz:
        try:
            import gsply  # noqa: F401
        except ImportError:
            raise InputError("--spz: needs the gsply package (pip install -e \".[spz]\")") from None
    if lod_dir is not None:
        from clod_adapter.io.splat_transform import NPM_INSTALL, find_splat_transform

        if find_splat_transform() is None:
            raise InputError(f"--lod-meta: splat-transform not found; install the pinned version with `{NPM_INSTALL}` "
                             "in the repository root (or set $CLOD_SPLAT_TRANSFORM)")
    if web_dir is not None:
        from clod_adapter.export.web import find_playcanvas

        if find_playcanvas() is None:
            raise InputError("--web: the PlayCanvas engine is not installed; run `npm ci` in the repository root")


def _check_outputs(out: Path, ply: Path, names: list, folders: list, force: bool) -> None:
    """``out`` with ``names``, and each (folder, its names) of ``folders`` that is given: new or
    empty (or ``force``), not the input; a folder equal to ``out`` adds its names to ``out``'s."""
    names = list(names)
    for d, files in folders:
        if d is not None and d.resolve() == out.resolve():
            names += files
    jobs.check_output_dir(out, [ply], names, create=False, force=force)
    for d, files in folders:
        if d is not None and d.resolve() != out.resolve():
            jobs.check_output_dir(d, [ply], files, create=False, force=force)


def _main(args, argv) -> int:
    if not args.output:  # `--lod-meta DIR` or `--web DIR` alone: DIR holds everything
        args.output = args.lod_meta or args.web
    if not args.ply or not args.images or not args.output:
        raise InputError("give ADAPTED, --images SCENE and -o OUTDIR")
    ply, scene_root, out = Path(args.ply), Path(args.images), Path(args.output)
    lod_dir = None if args.lod_meta is None else Path(args.lod_meta or args.output)
    web_dir = None if args.web is None else Path(args.web or args.output)
    if args.s_v is not None:
        check_flag(math.isfinite(args.s_v) and args.s_v >= 1, "--s-v", "a number >= 1", args.s_v)
    budget = None
    if args.budget is not None:
        budget = common.parse_budget(args.budget, "--budget")
        if budget == 0:
            raise InputError(f"--budget must be > 0 (a count or a fraction <= 1), got {args.budget}")
    if args.sog_sh_iterations is not None:
        check_flag(args.sog_sh_iterations >= 1, "--sog-sh-iterations", ">= 1", args.sog_sh_iterations)
        if args.lod_meta is None:
            raise InputError("--sog-sh-iterations applies to --lod-meta only")
    if args.sh_max_drop_db is not None:
        check_flag(math.isfinite(args.sh_max_drop_db) and args.sh_max_drop_db >= 0, "--sh-max-drop-db", ">= 0",
                   args.sh_max_drop_db)
    if not ply.exists():
        raise InputError(f"{ply}: no such file")
    if not scene_root.is_dir():
        raise InputError(f"{scene_root}: no such scene folder")
    _check_tools(args.spz, lod_dir, web_dir)
    common.set_threads(args.threads)

    from clod_adapter.io.load import resolve_model_path
    from clod_adapter.jobs.export import EXTENDED_NAME, JSON_NAME, ORDERED_NAME, ExportOptions, export, summary
    from clod_adapter.io.ply import read_ply
    from clod_adapter.io.load import load_scene

    ply = resolve_model_path(ply, prefer="point_cloud.ply")
    baked_name = None
    if args.s_v is not None:
        baked_name = f"baked_sv{_fmt(args.s_v)}.ply"
    elif budget is not None:
        baked_name = f"baked_budget{_fmt(budget)}.ply"
    names = [EXTENDED_NAME, JSON_NAME] + ([ORDERED_NAME] if args.ordered else []) + ([baked_name] if baked_name else [])
    if args.spz:
        names += [Path(n).with_suffix(".spz").name for n in names if n.endswith(".ply")]
    from clod_adapter.io.splat_transform import LOD_META_NAME

    _check_outputs(out, ply, names, [(lod_dir, [LOD_META_NAME]), (web_dir, ["index.html"])], args.force)
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
    options = ExportOptions(s_v=args.s_v, budget=budget, baked_name=baked_name, ordered=args.ordered,
                            prune=args.prune, sh_max_drop_db=args.sh_max_drop_db, spz=args.spz,
                            lod_dir=lod_dir, sog_sh_iterations=args.sog_sh_iterations, web_dir=web_dir,
                            progress=not args.quiet, argv=argv)
    report = export(model.to(dev), scene, train_imgs, test_cams, test_imgs, out, ply, options)
    print(summary(report))
    print(f"clod-export: wrote {', '.join(report['files'])} to {out} in {report['seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
