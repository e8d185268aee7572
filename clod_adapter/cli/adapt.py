"""``clod-adapt``: give a trained 3DGS checkpoint a continuous level of detail (CLoD-GS).

    clod-adapt MODEL --images SCENE --max-sv 5 [-o OUT] [--iterations N] [--resolution R]
               [--device auto|cpu|cuda] [--seed S] [--resume] [--force] [--sanitize] [--masks P]
               [--deterministic] [--layout inria] [--allow-mismatch]
    clod-adapt -m MODEL_FOLDER -s SCENE ...        (the official 3DGS spelling)
    clod-adapt --demo [-o OUT]
    torchrun --nproc_per_node=N -m clod_adapter.cli.adapt MODEL --images SCENE ...   (data-parallel; or --distributed)

MODEL: a .ply / gsplat .pt, an official 3DGS model folder (``point_cloud/iteration_N/``, the
latest N unless ``--iteration``) or a folder holding one .ply.

Exit status: 0 done, 2 bad input (one line on stderr, nothing written), 130 interrupted (the
resumable state is saved in OUT), 1 data-parallel run that lost a process (one line saying
which state is on disk).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from clod_adapter.cli import common
from clod_adapter.cli.common import check_flag
from clod_adapter.errors import InputError

EXAMPLE = ("clod-adapt ../shared/data/fern/pretrained -s ../shared/data/fern --resolution 2 --max-sv 5 "
           "-o runs/fern")


def _shares(text: str) -> tuple:
    """``--parent-share``'s value: comma-separated shares (``0`` or empty: none)."""
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected shares like 0.5,0.15,0.04, got {text!r}") from None


def build_parser():
    p = common.make_parser(
        "clod-adapt",
        "Fine-tune a per-Gaussian distance decay sigma_d (CLoD-GS, Cheng et al. ICLR 2026) on a "
        "pretrained 3DGS model so one model renders from full detail down to a small fraction of its "
        "Gaussians.", EXAMPLE)
    p.add_argument("ply", nargs="?", metavar="MODEL",
                   help="pretrained 3DGS model: .ply (INRIA layout, MaskGaussian, PlayCanvas/SuperSplat "
                        "compressed), a gsplat ckpt_*.pt, an official model folder "
                        "(point_cloud/iteration_N/point_cloud.ply) or a folder holding one .ply")
    p.add_argument("-m", "--model_path", "--model-path", dest="model_path", metavar="MODEL",
                   help="the same as MODEL (the official 3DGS flag)")
    p.add_argument("--iteration", type=int, default=None, metavar="N",
                   help="with a model folder: use point_cloud/iteration_N (default: the largest N)")
    common.add_scene_flags(p, resolution_note="; use the resolution the checkpoint was trained at")
    p.add_argument("--max-sv", type=float, default=5.0, help="largest virtual distance scale trained (default 5)")
    p.add_argument("-o", "--output", metavar="OUT",
                   help="output folder, new or empty (default: ./clod_out; demo ./clod_demo)")
    p.add_argument("--iterations", type=int, default=None, help="optimisation steps (default 1000; demo 400)")
    p.add_argument("--background", default="black", choices=("black", "white"),
                   help="colour behind the scene (NeRF-synthetic RGBA images are composited over it)")
    p.add_argument("--seed", type=int, default=0, help="seed of the view order and s_v sampling (default 0)")
    p.add_argument("--schedule", default="calibrated", choices=("calibrated", "paper"),
                   help="training recipe: 'calibrated' (default; sigma_d mapped from a ranking so s_v draws "
                        "s_v^-1.5 of the Gaussians, window fade, level gains) or 'paper' (CLoD-GS: Eq. 2 fading, "
                        "L_reg); docs/method.md")
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
    p.add_argument("--level-max", type=float, default=1.0, metavar="L",
                   help="calibrated schedule: largest level of the gains (default 1: held at 1 below max_sv^-1.5 "
                        "of the Gaussians in view); 2 grows them on (better far below, worse mid-range on skull; "
                        "docs/studies.md)")
    _tier_flags(p)
    p.add_argument("--faint-share", type=float, default=None, metavar="SHARE",
                   help="leave out first the Gaussians whose blending weight summed over every training view is "
                        "under SHARE of one view's pixels (default 1e-5 with the calibrated schedule, about 2 px; "
                        "0, and the paper's schedule: every Gaussian; chosen on validation views, docs/studies.md)")
    p.add_argument("--keep-share", type=float, default=1.0, metavar="SHARE",
                   help="leave out what the scene does not need first: keep SHARE of the input's Gaussians, the top "
                        "by blending weight over the training views, and recover them (every attribute, "
                        "--recovery-steps) before the LoD is learned; full detail is then the kept model "
                        "(default 1: every Gaussian --faint-share keeps; "
                        "docs/method.md)")
    p.add_argument("--recovery-steps", type=int, default=1000, metavar="N",
                   help="with --keep-share < 1: recovery steps, kept when the last one beats the static cut on "
                        "held-out training views (default 1000; 0: the static cut)")
    p.add_argument("--tau", type=float, default=None, help="LoD threshold: render iff alpha'' > tau*s_v (default 0.005)")
    p.add_argument("--eta-estimator", default=None, choices=("ste", "sigmoid", "paper"),
                   help="paper schedule: gradient of the rendered fraction in L_reg (default 'ste'); "
                        "'paper' = hard count, no gradient")
    _run_flags(p)
    return p


def _tier_flags(p) -> None:
    """The merged tiers: which shares of the input (AdaptConfig's ``parent_share``). How each tier
    is built, fitted and handed over (``tier_*``, ``tree_steps``, ``tree_budget_steps``) are
    AdaptConfig's, chosen on validation views (docs/studies.md) and set by the benchmarks'
    ``--config KEY=VALUE`` for a study, not flags: ``--iterations`` bounds every one of their steps."""
    p.add_argument("--parent-share", type=_shares, default=None, metavar="SHARE[,SHARE...]",
                   help="calibrated schedule: the merge tree's tiers, each SHARE of the input's Gaussians "
                        "(descending), each drawn where it pays (default 0.5,0.15,0.04; 0: none, a smaller file "
                        "and a shorter job; left out under 10,000 Gaussians or without splat-transform; "
                        "docs/method.md)")


def _run_flags(p) -> None:
    """How the run goes (inputs' handling, saves, outputs, timing, processes): AdaptOptions'."""
    p.add_argument("--masks", default="auto", choices=("auto", "argmax", "gumbel", "all"),
                   help="a MaskGaussian .ply with mask scores (masks_0/masks_1): keep p(keep) > 0.5 "
                        "('argmax', the default 'auto'), one Gumbel draw as MaskGaussian's own save "
                        "('gumbel', seeded by --seed) or every Gaussian ('all'); the log says how many were kept")
    p.add_argument("--sanitize", action="store_true",
                   help="drop Gaussians with NaN/Inf values (and clamp +Inf opacity logits to "
                        "logit(1 - 1e-7)) instead of stopping; says how many")
    p.add_argument("--allow-mismatch", action="store_true",
                   help="go on when the model renders the training views no better than a flat colour "
                        "(a model from another scene); refused by default")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/adapt_state.safetensors (give the same MODEL, scene and flags; "
                        "--iterations defaults to the saved run's)")
    p.add_argument("--deterministic", action="store_true",
                   help="bit-reproducible CPU gradients (static tile schedule, fixed reduction order; "
                        "somewhat slower): a resumed run then ends identical to an uninterrupted one "
                        "(same seed and thread count). Also CLOD_DETERMINISTIC=1")
    p.add_argument("--layout", default="clod", choices=("clod", "inria"),
                   help="inria: also write the official model folder (point_cloud/iteration_N/point_cloud.ply "
                        "in the exact INRIA layout, cameras.json, cfg_args) for SIBR-style viewers and scripts")
    p.add_argument("--tensorboard", action="store_true",
                   help="log loss, PSNR, s_v and rendered fraction per step to OUT/tensorboard "
                        "(needs pip install -e \".[tensorboard]\")")
    p.add_argument("--timing-repeats", type=int, default=3, metavar="R",
                   help="interleaved timing rounds for the final ms/frame (default 3; 0: time the single "
                        "evaluation pass)")
    p.add_argument("--views-per-step", type=int, default=None, metavar="V",
                   help="training views per optimisation step, each at its own s_v, gradients averaged "
                        "(default 1; data-parallel: the number of processes; --resume: the saved run's)")
    p.add_argument("--distributed", action="store_true",
                   help="data-parallel over views with torch.distributed, reading torchrun's environment "
                        "(RANK, WORLD_SIZE, MASTER_ADDR, MASTER_PORT; gloo on CPU, NCCL on GPUs); implied "
                        "when started by torchrun: torchrun --nproc_per_node=N -m clod_adapter.cli.adapt ...")
    p.add_argument("--save-every", type=int, default=None, metavar="N",
                   help="also write the resumable state every N steps (default: every 10 %% of the run when "
                        "data-parallel, else only on a signal and at the end; 0: never)")
    p.add_argument("--holdout-val", action="store_true",
                   help=argparse.SUPPRESS)  # benchmarks' --split val: fit without the validation views, score on them
    p.add_argument("--demo", action="store_true",
                   help="build the embedded synthetic scene and pretrained model in OUT/demo and adapt it")
    common.add_common_flags(p)


def _config(args, world: int):
    """The run's AdaptConfig from the flags; its own checks (AdaptConfig.__post_init__, the one
    place the settings' rules live) reported with the flag's name."""
    from clod_adapter.train.config import AdaptConfig

    iterations = args.iterations if args.iterations is not None else (400 if args.demo else 1000)
    kw = {} if args.tau is None else {"tau": args.tau}
    try:
        return AdaptConfig(max_sv=args.max_sv, iterations=iterations, seed=args.seed, schedule=args.schedule,
                           other_lr_scale=args.other_lr_scale, lambda_reg=args.lambda_reg,
                           fade=args.fade, gains=args.gains, eta_estimator=args.eta_estimator or "ste",
                           background=(1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0),
                           views_per_step=args.views_per_step if args.views_per_step is not None else world,
                           level_max=args.level_max, parent_share=args.parent_share, faint_share=args.faint_share,
                           keep_share=args.keep_share, recovery_steps=args.recovery_steps, **kw)
    except ValueError as e:  # "<field> must be ...": the field is the flag
        field, _, rest = str(e).partition(" ")
        raise InputError(f"--{field.replace('_', '-')} {rest}") from None


#: exit status of a data-parallel run that lost one of its processes.
EXIT_PEER_LOST = 1


def main(argv: list[str] | None = None) -> int:
    common.thread_defaults()  # before torch is imported (OpenMP reads it when it loads)
    args = build_parser().parse_args(argv)

    def body() -> int:
        try:
            return _main(args)
        except RuntimeError as e:
            from clod_adapter.train.distributed import PeerLost

            if not isinstance(e, PeerLost):
                raise
            print(f"clod-adapt: error: {common.one_line(e)}", file=sys.stderr, flush=True)
            return EXIT_PEER_LOST
    code = common.run_cli("clod-adapt", body)
    if "clod_adapter.train.distributed" in sys.modules:  # a data-parallel process: end it without the
        from clod_adapter.train.distributed import exit_process  # interpreter's shutdown (see there)

        return exit_process(code)
    return code


def _main(args) -> int:
    if args.ply and args.model_path and args.ply != args.model_path:
        raise InputError("give the model once: MODEL or -m/--model_path")
    model = args.ply or args.model_path
    if args.lambda_reg is not None:
        check_flag(args.lambda_reg >= 0, "--lambda-reg", ">= 0", args.lambda_reg)
    if args.schedule == "calibrated":  # flags of the paper's count regulariser: nothing to act on
        for flag, value in (("--lambda-reg", args.lambda_reg), ("--eta-estimator", args.eta_estimator)):
            if value is not None:
                raise InputError(f"{flag} acts on the paper schedule's count regulariser only; "
                                 "the calibrated schedule has none (add --schedule paper)")
    check_flag(args.timing_repeats >= 0, "--timing-repeats", ">= 0", args.timing_repeats)
    if args.iteration is not None:
        check_flag(args.iteration >= 0, "--iteration", ">= 0", args.iteration)
    if args.save_every is not None:
        check_flag(args.save_every >= 0, "--save-every", ">= 0", args.save_every)
    from clod_adapter.train.distributed import launched_by_torchrun

    distributed = args.distributed or launched_by_torchrun()
    if args.distributed and not launched_by_torchrun():
        raise InputError("--distributed: RANK, WORLD_SIZE, MASTER_ADDR, MASTER_PORT are not set; start it with "
                         "torchrun --nproc_per_node=N -m clod_adapter.cli.adapt ...")
    if distributed and args.demo:
        raise InputError("--demo runs in one process; build the demo first (clod-adapt --demo -o OUT), then "
                         "torchrun ... -m clod_adapter.cli.adapt OUT/demo/pretrained/point_cloud.ply --images OUT/demo/scene")
    world = int(os.environ.get("WORLD_SIZE", "1")) if distributed else 1
    common.set_threads(args.threads)
    # Imports after parsing so --help is instant.
    from clod_adapter.jobs.adapt import AdaptOptions, run

    out = Path(args.output or ("clod_demo" if args.demo else "clod_out"))
    force = args.force
    cfg = _config(args, world)  # checked before anything is written (the demo scene included)
    if args.demo:
        from clod_adapter.jobs.adapt_inputs import check_output_dir
        from clod_adapter.io.synthetic import build_demo_scene

        check_output_dir(out, [], create=False, force=args.force, resume=args.resume)
        scene, ply = build_demo_scene(out / "demo")
        force = True  # checked above; OUT now holds the demo scene
        print(f"clod-adapt: demo scene written to {scene}, pretrained stand-in {ply}")
    else:
        if not model or not args.images:
            raise InputError("give MODEL and --images SCENE (or -m MODEL -s SCENE, or --demo)")
        scene, ply = Path(args.images), Path(model)
    options = AdaptOptions(resolution=args.resolution, device=args.device, resume=args.resume,
                           progress=not args.quiet, sanitize=args.sanitize, deterministic=args.deterministic,
                           iterations_from_state=args.resume and args.iterations is None, force=force,
                           allow_mismatch=args.allow_mismatch, iteration=args.iteration, layout=args.layout,
                           tensorboard=args.tensorboard, timing_repeats=args.timing_repeats, masks=args.masks,
                           distributed=distributed, save_every=args.save_every,
                           views_from_state=args.resume and args.views_per_step is None,
                           holdout_val=args.holdout_val)
    run(ply, scene, out, cfg, options)
    return 0


if __name__ == "__main__":
    sys.exit(main())
