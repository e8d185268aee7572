"""``clod-eval``: what each level of detail of an adapted CLoD-GS model costs and loses.

    clod-eval OUT/point_cloud.ply --images SCENE [--pretrained PRE.ply] [--resolution R]
              [--budgets 1,0.5,0.25,0.1] [--sv-steps 25] [--max-sv X] [--lpips-weights PATH]
              [--sigma-c C] [--device auto|cpu|cuda] -o REPORT

Writes REPORT/{report.csv, report_per_view.csv, report.json, report.md, quality_vs_gaussians.png,
quality_vs_time.png, popping.png, lod_strip.png} (see :mod:`clod_adapter.report`).

Exit status: 0 done, 2 bad input (one line on stderr naming the file or flag, nothing written),
130 interrupted.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="clod-eval",
        description="Sweep an adapted CLoD-GS model over s_v and hard Gaussian budgets, compare it with "
                    "baselines cut from the pretrained model at the same counts, measure popping, "
                    "and write a report (CSV, JSON, plots).",
    )
    p.add_argument("ply", nargs="?", help="adapted model .ply (with sigma_d; from clod-adapt)")
    p.add_argument("--images", metavar="SCENE",
                   help="scene folder: COLMAP (images/, sparse/0) or NeRF-synthetic (transforms_*.json)")
    p.add_argument("--pretrained", metavar="PRE.ply",
                   help="pretrained model the baselines cut: .ply (INRIA, compressed) or gsplat ckpt .pt "
                        "(default: the adapted model without sigma_d)")
    p.add_argument("--resolution", type=int, default=1, choices=(1, 2, 4, 8),
                   help="use images_R/ when present, else downsample by R (default 1)")
    p.add_argument("--budgets", default=None,
                   help="comma-separated budgets: values <= 1 are fractions, integers > 1 counts "
                        "(default 1,0.5,0.25,0.1 down to max_sv^-1.5, and max_sv^-1.5)")
    p.add_argument("--sv-steps", type=int, default=25, help="points of the s_v sweep (default 25)")
    p.add_argument("--max-sv", type=float, default=None,
                   help="trained maximum s_v (default: from adapt_state.safetensors beside PLY, else 5); "
                        "the sweep goes to 1.2x this")
    p.add_argument("--popping-steps", type=int, default=61, help="frames of the popping sweep (default 61)")
    p.add_argument("--lpips-weights", metavar="PATH",
                   help="LPIPS-alex weights (.safetensors); default $CLOD_LPIPS_WEIGHTS, then "
                        "../shared/data/lpips/; LPIPS is skipped with a note when none exists")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    p.add_argument("--sigma-c", type=float, default=None,
                   help="constant sigma_d of the constant-sigma baseline (default: the best of a grid on "
                        "training views at 50 %% of the Gaussians)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random baseline")
    p.add_argument("--dlod-iterations", type=int, default=None,
                   help="steps of the per-budget ceiling dlod_finetuned (one fine-tuned model per budget; "
                        "default: the adaptation's iterations from adapt_state.safetensors, else 1000; 0 skips)")
    p.add_argument("--splat-transform", metavar="EXE", default=None,
                   help="splat-transform executable for the merging-decimator baseline 'merge' (default: "
                        "$CLOD_SPLAT_TRANSFORM or splat-transform on PATH; skipped with a note when absent)")
    p.add_argument("--no-merge", action="store_true", help="skip the merging-decimator baseline")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    p.add_argument("--background", default="black", choices=("black", "white"),
                   help="colour behind the scene (NeRF-synthetic RGBA images are composited over it)")
    p.add_argument("-o", "--output", metavar="REPORT", help="report folder (default: ./clod_report)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from clod_adapter.io.ply import PlyFormatError, read_ply
    from clod_adapter.io.scene import SceneError
    from clod_adapter.io.scenes import load_scene
    from clod_adapter.pipeline import InputError, pick_device
    from clod_adapter.report import (check_report_dir, evaluate_report, iterations_from_state, max_sv_from_state,
                                     normalize_budgets)

    def bad(msg: str) -> int:
        print(f"clod-eval: error: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT

    if not args.ply or not args.images:
        return bad("give PLY and --images SCENE")
    ply, scene_root = Path(args.ply), Path(args.images)
    out = Path(args.output or "clod_report")
    try:
        if not ply.is_file():
            raise InputError(f"{ply}: no such file")
        if not scene_root.is_dir():
            raise InputError(f"{scene_root}: no such scene folder")
        if args.budgets is not None:
            try:
                budgets = normalize_budgets([float(x) for x in args.budgets.split(",") if x.strip()])
            except ValueError as e:
                raise InputError(f"--budgets {args.budgets!r}: {e}") from None
            if not budgets:
                raise InputError("--budgets: give at least one budget")
        if args.dlod_iterations is not None and args.dlod_iterations < 0:
            raise InputError(f"--dlod-iterations must be >= 0, got {args.dlod_iterations}")
        if args.splat_transform is not None and not Path(args.splat_transform).is_file():
            raise InputError(f"{args.splat_transform}: no such file (--splat-transform)")
        if args.sv_steps < 2:
            raise InputError(f"--sv-steps must be >= 2, got {args.sv_steps}")
        if args.popping_steps < 2:
            raise InputError(f"--popping-steps must be >= 2, got {args.popping_steps}")
        if args.max_sv is not None and not args.max_sv >= 1:
            raise InputError(f"--max-sv must be >= 1, got {args.max_sv}")
        if args.sigma_c is not None and not args.sigma_c > 0:
            raise InputError(f"--sigma-c must be > 0, got {args.sigma_c}")
        if args.lpips_weights is not None and not Path(args.lpips_weights).is_file():
            raise InputError(f"{args.lpips_weights}: no such LPIPS weights file (--lpips-weights)")
        dev = pick_device(args.device)
        adapted = read_ply(ply)
        if len(adapted) == 0:
            raise InputError(f"{ply}: the model has no Gaussians")
        if adapted.sigma_d is None:
            raise InputError(f"{ply}: no sigma_d property; not an adapted model (run clod-adapt first)")
        pretrained = None
        inputs = [ply]
        if args.pretrained is not None:
            pre = Path(args.pretrained)
            if not pre.is_file():
                raise InputError(f"{pre}: no such file (--pretrained)")
            from clod_adapter.io.load import load_model

            pretrained = load_model(pre)
            if len(pretrained) == 0:
                raise InputError(f"{pre}: the model has no Gaussians")
            inputs.append(pre)
        bg = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
        scene = load_scene(scene_root, resolution=args.resolution, background=bg)
        if not scene.cameras:
            raise InputError(f"{scene_root}: the scene has no views")
        lpips = None
        if not args.no_lpips:
            lpips = args.lpips_weights if args.lpips_weights is not None else "auto"
            if lpips != "auto":
                from clod_adapter.lpips import load_lpips

                try:
                    load_lpips(lpips)
                except ValueError as e:
                    raise InputError(str(e).splitlines()[0]) from None
        max_sv = args.max_sv if args.max_sv is not None else (adapted.lod.max_sv if adapted.lod else None) \
            or max_sv_from_state(ply) or 5.0
        if args.budgets is None:
            from clod_adapter.pipeline import budget_levels

            budgets = budget_levels(max_sv)
        dlod_it = args.dlod_iterations
        if dlod_it is None:
            dlod_it = iterations_from_state(ply) or 1000
        merge_tool = None
        if not args.no_merge:
            from clod_adapter.baselines import find_splat_transform

            merge_tool = args.splat_transform or find_splat_transform()
            if merge_tool is None:
                print("clod-eval: note: splat-transform not found; the 'merge' baseline is skipped "
                      "(npm install -g @playcanvas/splat-transform)", file=sys.stderr)
        check_report_dir(out, inputs)
        evaluate_report(ply, scene, out, pretrained=pretrained, pretrained_label=args.pretrained, budgets=budgets, max_sv=max_sv,
                        sv_steps=args.sv_steps, popping_steps=args.popping_steps, lpips=lpips,
                        seed=args.seed, sigma_c=args.sigma_c, device=dev, progress=not args.quiet,
                        background=bg, dlod_iterations=dlod_it, merge_tool=merge_tool)
        print(f"clod-eval: wrote the report to {out}")
    except (InputError, PlyFormatError, SceneError) as e:
        return bad(" ".join(str(e).split("\n")))
    except OSError as e:  # an unreadable input or unwritable output the checks above missed
        return bad(f"{e.filename if e.filename is not None else 'clod-eval'}: {e.strerror or e}")
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    return 0


if __name__ == "__main__":
    sys.exit(main())
