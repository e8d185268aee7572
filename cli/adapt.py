"""``clod-adapt``: give a trained 3DGS checkpoint a continuous level of detail (CLoD-GS).

    clod-adapt PLY --images SCENE --max-sv 5 [-o OUT] [--iterations N] [--resolution R]
               [--device auto|cpu|cuda] [--seed S] [--resume] [--sanitize]
               [--deterministic]
    clod-adapt --demo [-o OUT]

Exit status: 0 done, 2 bad input (one line on stderr, nothing written), 130 interrupted (the
resumable state is saved in OUT).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="clod-adapt",
        description="Fine-tune a per-Gaussian distance decay sigma_d (CLoD-GS, Cheng et al. ICLR 2026) "
                    "on a pretrained 3DGS .ply so one model renders from full detail down to a small "
                    "fraction of its Gaussians.",
    )
    p.add_argument("ply", nargs="?", help="pretrained 3DGS model: .ply (INRIA layout, MaskGaussian, "
                                          "PlayCanvas/SuperSplat compressed) or a gsplat ckpt_*.pt")
    p.add_argument("--images", metavar="SCENE",
                   help="scene folder: COLMAP (images/, sparse/0) or NeRF-synthetic (transforms_*.json)")
    p.add_argument("--max-sv", type=float, default=5.0, help="largest virtual distance scale trained (default 5)")
    p.add_argument("-o", "--output", metavar="OUT", help="output folder (default: ./clod_out)")
    p.add_argument("--iterations", type=int, default=None, help="optimisation steps (default 1000; demo 400)")
    p.add_argument("--resolution", type=int, default=1, choices=(1, 2, 4, 8),
                   help="use images_R/ when present, else downsample by R (default 1)")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    p.add_argument("--background", default="black", choices=("black", "white"),
                   help="colour behind the scene (NeRF-synthetic RGBA images are composited over it)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--schedule", default="calibrated", choices=("calibrated", "paper"),
                   help="training recipe: 'calibrated' (default; sigma_d mapped from a ranking so s_v draws "
                        "s_v^-1.5 of the Gaussians, window fade, level gains) or 'paper' (CLoD-GS: Eq. 2 fading, "
                        "L_reg); README 'How the whole range is kept'")
    p.add_argument("--other-lr-scale", type=float, default=None,
                   help="factor on the official 3DGS learning rates of the base attributes; 0 freezes them "
                        "(default: 0 calibrated, full detail stays the input; 0.1 paper)")
    p.add_argument("--lambda-reg", type=float, default=None,
                   help="paper schedule: weight of the rendered-count regulariser (default 0.05; the paper's 1 "
                        "is for training from scratch)")
    p.add_argument("--fade", default=None, choices=("window", "eq2"),
                   help="how survivors are drawn: 'window' (only Gaussians about to leave fade; calibrated "
                        "default) or 'eq2' (the paper's attenuation; paper default)")
    p.add_argument("--gains", default=None, metavar="LETTERS",
                   help="calibrated schedule: level gains to learn, letters of o (opacity), s (scale), "
                        "c (colour); default 'osc'; '' for none")
    p.add_argument("--tau", type=float, default=None, help="LoD threshold: render iff alpha'' > tau*s_v (default 0.005)")
    p.add_argument("--eta-estimator", default="ste", choices=("ste", "sigmoid", "paper"),
                   help="gradient of the rendered fraction in L_reg; 'paper' = hard count, no gradient")
    p.add_argument("--sanitize", action="store_true",
                   help="drop Gaussians with NaN/Inf values (and clamp +Inf opacity logits to "
                        "logit(1 - 1e-7)) instead of stopping; says how many")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/adapt_state.safetensors (give the same PLY, scene and flags; "
                        "--iterations defaults to the saved run's)")
    p.add_argument("--deterministic", action="store_true",
                   help="bit-reproducible CPU gradients (static tile schedule, fixed reduction order; "
                        "somewhat slower): a resumed run then ends identical to an uninterrupted one "
                        "(same seed and thread count). Also CLOD_DETERMINISTIC=1")
    p.add_argument("--demo", action="store_true",
                   help="build the embedded synthetic scene and pretrained model in OUT/demo and adapt it")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _one_line(e: object) -> str:
    """The message of ``e`` on one line (bad-input errors promise exactly one stderr line)."""
    return " ".join(str(e).split("\n")).strip()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Imports after parsing so --help is instant.
    from clod_adapter.adapt import AdaptConfig
    from clod_adapter.io.ply import PlyFormatError
    from clod_adapter.io.scene import SceneError
    from clod_adapter.pipeline import InputError, run

    out = Path(args.output or ("clod_demo" if args.demo else "clod_out"))
    try:
        if args.demo:
            from clod_adapter.synthetic import build_demo_scene

            scene, ply = build_demo_scene(out / "demo")
            print(f"clod-adapt: demo scene written to {scene}, pretrained stand-in {ply}")
            iterations = 400 if args.iterations is None else args.iterations
        else:
            if not args.ply or not args.images:
                print("clod-adapt: error: give PLY and --images SCENE (or --demo)", file=sys.stderr)
                return EXIT_BAD_INPUT
            scene, ply = Path(args.images), Path(args.ply)
            iterations = 1000 if args.iterations is None else args.iterations
        kw = {} if args.tau is None else {"tau": args.tau}
        cfg = AdaptConfig(max_sv=args.max_sv, iterations=iterations, seed=args.seed, schedule=args.schedule,
                          other_lr_scale=args.other_lr_scale, lambda_reg=args.lambda_reg,
                          fade=args.fade, gains=args.gains, eta_estimator=args.eta_estimator,
                          background=(1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0), **kw)
        run(ply, scene, out, cfg, resolution=args.resolution, device=args.device,
            resume=args.resume, progress=not args.quiet, sanitize=args.sanitize,
            deterministic=args.deterministic,
            iterations_from_state=args.resume and args.iterations is None)
    except (InputError, PlyFormatError, SceneError) as e:
        print(f"clod-adapt: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ValueError as e:  # config validation
        print(f"clod-adapt: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as e:  # an unreadable input or unwritable output the checks above missed
        name = e.filename if e.filename is not None else "clod-adapt"
        print(f"clod-adapt: error: {name}: {e.strerror or e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    return 0


if __name__ == "__main__":
    sys.exit(main())
