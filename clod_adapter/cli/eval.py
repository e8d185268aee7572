"""``clod-eval``: what each level of detail of an adapted CLoD-GS model costs and loses.

    clod-eval OUT[/point_cloud.ply] --images SCENE [--pretrained PRE] [--resolution R]
              [--budgets 1,0.5,0.25,0.1] [--sv-steps 25] [--max-sv X] [--lpips-weights PATH]
              [--sigma-c C] [--timing-repeats 3] [--device auto|cpu|cuda] [--force] -o REPORT

Writes REPORT/{report.md (opens with the verdict: where the adapted model is ahead of the best peer
at equal frame time and within equal count budgets, and by how much), quality_vs_time.png,
quality_vs_time.csv, report.csv, report_per_view.csv, report.json, quality_vs_gaussians.png,
levels_vs_time.png, popping.png, lod_strip.png} (see :mod:`clod_adapter.jobs.eval`).

Exit status: 0 done, 2 bad input (one line on stderr naming the file or flag, nothing written),
130 interrupted.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from clod_adapter import jobs
from clod_adapter.cli import common
from clod_adapter.cli.common import check_flag
from clod_adapter.errors import InputError

EXAMPLE = ("clod-eval runs/skull --images ../shared/data/skull --pretrained ../shared/data/skull/pretrained "
           "-o runs/skull_report")


def build_parser():
    p = common.make_parser(
        "clod-eval",
        "Quality against frame time of an adapted CLoD-GS model: compare it with the peers a user already "
        "has (LightGaussian and opacity cuts, splat-transform's decimators) at equal frame time and within "
        "equal count budgets, sweep it over s_v and budgets, measure popping, and write a report with a verdict "
        "(Markdown, CSV, JSON, plots).", EXAMPLE)
    common.add_adapted_inputs(p)
    p.add_argument("--pretrained", metavar="PRE",
                   help="pretrained model the baselines cut: .ply (INRIA, compressed), gsplat ckpt .pt, an "
                        "official model folder or a folder holding one .ply (default: the adapted model "
                        "without sigma_d)")
    p.add_argument("--iteration", type=int, default=None, metavar="N",
                   help="with a --pretrained model folder: use point_cloud/iteration_N (default: the largest)")
    p.add_argument("--budgets", default=None,
                   help="comma-separated budgets: values <= 1 are fractions, integers > 1 counts "
                        "(default 1,0.5,0.25,0.1 down to max_sv^-1.5, and max_sv^-1.5)")
    p.add_argument("--sv-steps", type=int, default=25, help="points of the s_v sweep (default 25)")
    p.add_argument("--max-sv", type=float, default=None,
                   help="trained maximum s_v (default: from adapt_state.safetensors beside the model, else 5); "
                        "the sweep goes to 1.2x this")
    p.add_argument("--popping-steps", type=int, default=61, help="frames of the popping sweep (default 61)")
    p.add_argument("--lpips-weights", metavar="PATH",
                   help="LPIPS-alex weights (.safetensors); default $CLOD_LPIPS_WEIGHTS, then "
                        "~/.cache/clod-adapter/; LPIPS is skipped with a note when none exists")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    p.add_argument("--sigma-c", type=float, default=None,
                   help="constant sigma_d of the constant-sigma baseline (default: the best of a grid on "
                        "training views at 50 %% of the Gaussians)")
    p.add_argument("--timing-repeats", type=int, default=3, metavar="R",
                   help="interleaved timing rounds after the quality pass (default 3; 0: time the quality "
                        "pass itself)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random baseline and the timing order (default 0)")
    p.add_argument("--dlod-iterations", type=int, default=0, metavar="N",
                   help="add the per-budget ceiling dlod_finetuned: one model per budget, the best static start "
                        "fine-tuned for N steps on the training views (the slowest part of a report: minutes per "
                        "budget; default 0: left out)")
    p.add_argument("--splat-transform", metavar="EXE", default=None,
                   help="splat-transform executable for the decimator baselines 'decimate' and 'decimate_adaptive' (default: "
                        "$CLOD_SPLAT_TRANSFORM, else node_modules/.bin/splat-transform as installed by `npm ci` "
                        "in the repository root, else PATH; skipped with a note when absent)")
    p.add_argument("--no-merge", action="store_true",
                   help="skip splat-transform's decimator baselines (the report says they were not run)")
    p.add_argument("--background", default="black", choices=("black", "white"),
                   help="colour behind the scene (NeRF-synthetic RGBA images are composited over it)")
    p.add_argument("-o", "--output", metavar="REPORT", help="report folder, new or empty (default: ./clod_report)")
    common.add_common_flags(p)
    return p


def main(argv: list[str] | None = None) -> int:
    common.thread_defaults()  # before torch is imported
    args = build_parser().parse_args(argv)
    return common.run_cli("clod-eval", lambda: _main(args))


def _check_flags(args) -> None:
    if not args.ply or not args.images:
        raise InputError("give ADAPTED and --images SCENE")
    check_flag(args.dlod_iterations >= 0, "--dlod-iterations", ">= 0", args.dlod_iterations)
    if args.splat_transform is not None and not Path(args.splat_transform).is_file():
        raise InputError(f"{args.splat_transform}: no such file (--splat-transform)")
    check_flag(args.sv_steps >= 2, "--sv-steps", ">= 2", args.sv_steps)
    check_flag(args.popping_steps >= 2, "--popping-steps", ">= 2", args.popping_steps)
    if args.max_sv is not None:
        check_flag(args.max_sv >= 1, "--max-sv", ">= 1", args.max_sv)
    if args.sigma_c is not None:
        check_flag(args.sigma_c > 0, "--sigma-c", "> 0", args.sigma_c)
    check_flag(args.timing_repeats >= 0, "--timing-repeats", ">= 0", args.timing_repeats)
    if args.lpips_weights is not None and not Path(args.lpips_weights).is_file():
        raise InputError(f"{args.lpips_weights}: no such LPIPS weights file (--lpips-weights)")


def _read_models(args, ply: Path):
    """(adapted .ply path, adapted model, pretrained path or None, pretrained model or None)."""
    from clod_adapter.io.load import load_model, resolve_model_path
    from clod_adapter.io.ply import read_ply

    ply = resolve_model_path(ply, prefer="point_cloud.ply")
    adapted = read_ply(ply)
    if len(adapted) == 0:
        raise InputError(f"{ply}: the model has no Gaussians")
    if adapted.sigma_d is None:
        raise InputError(f"{ply}: no sigma_d property; not an adapted model (run clod-adapt first)")
    if args.pretrained is None:
        if args.iteration is not None:
            raise InputError("--iteration applies to a --pretrained model folder")
        return ply, adapted, None, None
    pre = Path(args.pretrained)
    if not pre.exists():
        raise InputError(f"{pre}: no such file (--pretrained)")
    pre = resolve_model_path(pre, args.iteration, flag="--pretrained")
    pretrained = load_model(pre)
    if len(pretrained) == 0:
        raise InputError(f"{pre}: the model has no Gaussians")
    return ply, adapted, pre, pretrained


def _lpips_spec(args):
    """None (--no-lpips), "auto" or a checked weights file."""
    if args.no_lpips:
        return None
    lpips = args.lpips_weights if args.lpips_weights is not None else "auto"
    if lpips != "auto":
        from clod_adapter.evaluate.lpips import load_lpips

        try:
            load_lpips(lpips)
        except ValueError as e:
            raise InputError(str(e).splitlines()[0]) from None
    return lpips


def _merge_tool(args):
    """The splat-transform executable for the decimators, or None (--no-merge, or not found: said)."""
    if args.no_merge:
        return None
    from clod_adapter.io.splat_transform import find_splat_transform

    tool = args.splat_transform or find_splat_transform()
    if tool is None:
        print("clod-eval: note: splat-transform not found; the 'decimate' and 'decimate_adaptive' baselines "
              "are not run (install the pinned version with `npm ci` in the repository root)", file=sys.stderr)
    return tool


def _main(args) -> int:
    _check_flags(args)
    ply, scene_root = Path(args.ply), Path(args.images)
    out = Path(args.output or "clod_report")
    budgets = common.parse_budgets(args.budgets, "--budgets") if args.budgets is not None else None
    if not ply.exists():
        raise InputError(f"{ply}: no such file")
    if not scene_root.is_dir():
        raise InputError(f"{scene_root}: no such scene folder")
    common.set_threads(args.threads)

    from clod_adapter.train.state import max_sv_from_state
    from clod_adapter.io.splat_transform import PeerError
    from clod_adapter.io.load import load_scene, training_size
    from clod_adapter.jobs.adapt import METRICS_NAME
    from clod_adapter.jobs.adapt_inputs import resolution_note
    from clod_adapter.jobs.eval import OUTPUT_NAMES, EvalOptions, evaluate_report

    dev = jobs.pick_device(args.device)
    ply, adapted, pre, pretrained = _read_models(args, ply)
    inputs = [ply] + ([pre] if pre is not None else [])
    jobs.check_output_dir(out, inputs, OUTPUT_NAMES, create=False, force=args.force)
    bg = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
    scene = load_scene(scene_root, resolution=args.resolution, background=bg)
    if not scene.cameras:
        raise InputError(f"{scene_root}: the scene has no views")
    lpips = _lpips_spec(args)
    max_sv = args.max_sv if args.max_sv is not None else (adapted.lod.max_sv if adapted.lod else None) \
        or max_sv_from_state(ply) or 5.0
    if budgets is None:
        from clod_adapter.evaluate.level_metrics import budget_levels

        budgets = budget_levels(max_sv)
    dlod_it = args.dlod_iterations
    merge_tool = _merge_tool(args)
    cam0 = (scene.test or scene.train)[0]
    note = _resolution_note(ply, pre, (cam0.width, cam0.height), resolution_note, training_size, METRICS_NAME)
    jobs.check_output_dir(out, inputs, OUTPUT_NAMES, force=True)  # checked above; create
    options = EvalOptions(pretrained=pretrained, pretrained_label=str(pre) if pre else None, budgets=budgets,
                          max_sv=max_sv, sv_steps=args.sv_steps, popping_steps=args.popping_steps, lpips=lpips,
                          seed=args.seed, sigma_c=args.sigma_c, device=dev, progress=not args.quiet,
                          background=bg, timing_repeats=args.timing_repeats, notes=[note] if note else [],
                          dlod_iterations=dlod_it, merge_tool=merge_tool)
    try:
        report = evaluate_report(ply, scene, out, options)
    except PeerError as e:  # a peer that fails stops the report: it never silently drops out
        print(f"clod-eval: error: {common.one_line(e)} (--no-merge runs without the decimators)", file=sys.stderr)
        return 1
    print(f"clod-eval: wrote the report to {out} in {report['wall_seconds']:.0f} s (verdict: {out / 'report.md'})")
    return 0


def _resolution_note(ply, pre, size, resolution_note, training_size, metrics_name):
    """The aliasing note when the training size is known (cameras.json of a model folder, or the
    image size clod-adapt recorded in metrics.json beside the adapted model) and differs."""
    for path in (ply, pre):
        if path is None:
            continue
        ts = training_size(path)
        if ts:
            return resolution_note(ts, size, f"cameras.json beside {path}")
    m = Path(ply).parent / metrics_name
    if m.is_file():
        try:
            ts = json.loads(m.read_text()).get("image_size")
        except (ValueError, OSError):
            ts = None
        if ts:
            return resolution_note(tuple(ts), size, f"clod-adapt's {m}")
    return None


if __name__ == "__main__":
    sys.exit(main())
