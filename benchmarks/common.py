"""Shared by the benchmarks (``quality_vs_time.py``) and the studies (``studies/``): the inputs,
one cached adaptation per (input, settings), and the common command line.

Inputs (``INPUTS``):

* ``fern``: the vanilla 3DGS fern checkpoint, ``../shared/data/fern`` at ``images_2``;
* ``maskgaussian``: the MaskGaussian-pruned fern checkpoint on the same scene;
* ``skull``: the vanilla 3DGS skull checkpoint, a 360-degree capture, ``../shared/data/skull``;
* ``demo``: the embedded synthetic scene of ``clod-adapt --demo`` (another scene, built here);
* any checkpoint and scene: ``--input NAME=PLY:SCENE[:RES]`` (:func:`add_inputs_args`).

Adaptations are cached under ``RUNS/<input>/<tag>/`` (the ``clod-adapt`` output folder): a run
whose ``metrics.json`` holds the same settings is reused, so the benchmarks share them.

Splits (``--split``, :func:`scene_views`): ``test`` fits on the training views and scores on the
test views (what the README reports); ``val`` fits on the training views minus the validation
views (:func:`clod_adapter.io.scene.validation_split`) and scores on those, never touching a test
view. Benchmarks that *choose* settings (compare_configs.py, max_sv_sweep.py, lambda_sweep.py) default
to ``val``; their adaptations then run ``clod-adapt --holdout-val`` and are cached apart (tag
suffix ``_val``).
"""
from __future__ import annotations

import json
import shutil
import os
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Optional

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
RUNS = REPO / "runs" / "bench"
if (SHARED / "lpips" / "lpips_alex_v0.1.safetensors").is_file():  # the package looks in the user cache
    os.environ.setdefault("CLOD_LPIPS_WEIGHTS", str(SHARED / "lpips" / "lpips_alex_v0.1.safetensors"))

from clod_adapter.train.config import AdaptConfig  # noqa: E402
from clod_adapter.io.load import load_model  # noqa: E402
from clod_adapter.io.load import load_scene  # noqa: E402
from clod_adapter.io.scene import validation_split  # noqa: E402

FERN = SHARED / "fern"
INPUTS = {
    "fern": (FERN / "pretrained/point_cloud/iteration_7000/point_cloud.ply", FERN, 2),
    "maskgaussian": (FERN / "maskgaussian/point_cloud/iteration_8500/point_cloud.ply", FERN, 2),
    "skull": (SHARED / "skull" / "pretrained/point_cloud/iteration_5000/point_cloud.ply", SHARED / "skull", 1),
    "demo": (None, None, 1),
}
#: the inputs the shared data provides (``--input`` adds others to INPUTS).
SHARED_INPUTS = tuple(INPUTS)
LABELS = {"fern": "fern (forward-facing, vanilla 3DGS)", "maskgaussian": "fern, MaskGaussian-pruned",
          "skull": "skull (360-degree, vanilla 3DGS)", "demo": "synthetic demo scene"}


SPLITS = ("test", "val")


def add_split_arg(ap, default: str = "val") -> None:
    """``--split {test,val}`` on an argparse parser (see the module docstring)."""
    ap.add_argument("--split", choices=SPLITS, default=default,
                    help="views that score the settings: 'val' (training views held out of the fit; "
                         "for choosing) or 'test' (the held-out test views; for reporting) "
                         f"(default {default})")


def scene_views(scene, split: str) -> tuple[list, list]:
    """(cameras to fit on, cameras to score on) of ``scene`` for a split: ``"test"``: (train,
    test); ``"val"``: :func:`clod_adapter.io.scene.validation_split` of the training views (fit,
    val). A scene without test views scores ``"test"`` on its first training view."""
    if split == "test":
        return list(scene.train), list(scene.test) or list(scene.train[:1])
    if split == "val":
        return validation_split(scene.train)
    raise ValueError(f"split must be one of {SPLITS}, got {split!r}")


def register_input(spec: str) -> str:
    """Register ``NAME=PLY:SCENE[:RES]`` (a user's checkpoint and scene, ``RES`` the image
    downsampling, default 1) as an input of the benchmarks, and return ``NAME``.

    Raises:
        SystemExit: the spec has no ``NAME=``, no ``PLY:SCENE``, or a name of a shared input.
    """
    name, eq, rest = spec.partition("=")
    parts = rest.split(":")
    if not eq or not name or len(parts) not in (2, 3) or not all(parts[:2]):
        sys.exit(f"benchmark: --input {spec!r}: expected NAME=PLY:SCENE[:RES]")
    if name in INPUTS and INPUTS[name][0] is not None and str(INPUTS[name][0]) != parts[0]:
        sys.exit(f"benchmark: --input {spec!r}: {name!r} is a shared input's name; choose another")
    try:
        res = int(parts[2]) if len(parts) == 3 else 1
    except ValueError:
        sys.exit(f"benchmark: --input {spec!r}: RES must be an integer")
    INPUTS[name] = (Path(parts[0]), Path(parts[1]), res)
    LABELS.setdefault(name, f"{name} ({Path(parts[0]).name})")
    return name


def add_inputs_args(ap, default) -> None:
    """``--inputs NAME ...`` (the shared inputs: fern, maskgaussian, skull, demo) and
    ``--input NAME=PLY:SCENE[:RES]`` (repeatable: any checkpoint and scene) on a parser; read
    them back with :func:`selected_inputs`."""
    ap.add_argument("--inputs", nargs="+", default=None, metavar="NAME",
                    help=f"shared inputs ({', '.join(sorted(LABELS))}; default: {' '.join(default)}; "
                         "none when --input is given)")
    ap.add_argument("--input", action="append", default=[], metavar="NAME=PLY:SCENE[:RES]",
                    help="any pretrained checkpoint and its scene folder (RES: image downsampling, default 1); "
                         "repeatable")
    ap.set_defaults(_default_inputs=list(default))


def selected_inputs(args) -> list[str]:
    """The input names of a parsed command line (:func:`add_inputs_args`): ``--inputs`` (or the
    default when neither flag is given), then each ``--input``, registered."""
    names = list(args.inputs) if args.inputs is not None else ([] if args.input else list(args._default_inputs))
    for n in names:
        if n not in INPUTS:
            sys.exit(f"benchmark: unknown input {n!r} (shared: {', '.join(sorted(LABELS))}; "
                     "or --input NAME=PLY:SCENE[:RES])")
    return names + [register_input(s) for s in args.input]


def parse_inputs_args(doc: str, argv=None, inputs=("fern", "skull"), split: str = "test", extra=()):
    """The common command line of the per-input benchmarks (``--inputs``, ``--input``,
    ``--split``, ``--threads``, and ``extra``: (flag, add_argument keywords) pairs), parsed, with
    the threads set; ``.inputs`` holds the selected names (:func:`selected_inputs`)."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    add_inputs_args(ap, inputs)
    add_split_arg(ap, default=split)
    ap.add_argument("--threads", type=int, default=2)
    for flag, kw in extra:
        ap.add_argument(flag, **kw)
    a = ap.parse_args(argv)
    a.inputs = selected_inputs(a)
    setup_threads(a.threads)
    return a


def run_per_input(doc: str, run_input, argv=None, inputs=("fern", "skull")) -> None:
    """The main of a validation-view study: ``--inputs`` and ``--threads`` parsed, then
    ``run_input(name)`` for each input without autograd."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    add_inputs_args(ap, inputs)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    names = selected_inputs(a)
    setup_threads(a.threads)
    with torch.no_grad():
        for name in names:
            run_input(name)


def split_suffix(split: str) -> str:
    """Suffix of cache tags and output names: ``""`` for test, ``"_val"`` for val."""
    return "" if split == "test" else f"_{split}"


def setup_threads(n: int = 2) -> None:
    torch.set_num_threads(n)


def resolve_input(name: str) -> tuple[Path, Path, int]:
    """(pretrained .ply, scene folder, resolution) of an input name (shared, or registered by
    ``--input NAME=PLY:SCENE[:RES]``) or ``PLY:SCENE[:RES]``."""
    if name in INPUTS:
        ply, scene, res = INPUTS[name]
        if name == "demo":
            from clod_adapter.io.synthetic import build_demo_scene

            root = RUNS / "demo_input"
            scene, ply = root / "scene", root / "pretrained" / "point_cloud.ply"
            if not ply.is_file():
                build_demo_scene(root)
        if not Path(ply).is_file():
            where = "needs ../shared/data beside the repository" if name in SHARED_INPUTS else f"--input {name}"
            sys.exit(f"benchmark: {ply} not found ({where})")
        if not Path(scene).is_dir():
            sys.exit(f"benchmark: {scene}: no such scene folder (input {name})")
        return Path(ply), Path(scene), res
    parts = name.split(":")
    if len(parts) not in (2, 3):
        sys.exit(f"benchmark: unknown input {name!r} (fern, maskgaussian, demo or PLY:SCENE[:RES])")
    return Path(parts[0]), Path(parts[1]), int(parts[2]) if len(parts) == 3 else 1


def parse_config(items) -> tuple[dict, str]:
    """``KEY=VALUE`` strings (the benchmarks' ``--config``) as AdaptConfig settings, each value
    converted to its default's type (``none`` is None), and the cache tag naming them
    (``"default"`` for none).

    Raises:
        SystemExit: a key AdaptConfig does not have, or an item without ``=``.
    """
    from clod_adapter.train.config import AdaptConfig

    base, config = AdaptConfig(), {}
    for kv in items:
        k, eq, v = kv.partition("=")
        if not eq or not hasattr(base, k):
            sys.exit(f"benchmark: --config {kv!r}: expected KEY=VALUE with an AdaptConfig key")
        d = getattr(base, k)
        config[k] = (None if v.lower() == "none" else tuple(float(x) for x in v.split(",") if x)
                     if isinstance(d, tuple) else type(d)(v) if d is not None else v)
    tag = "_".join(f"{k}-{','.join(map(str, v)) if isinstance(v, tuple) else v}" for k, v in sorted(config.items()))
    return config, ("default" if not config else tag)


#: AdaptConfig keys added after runs were cached, with the value those runs had.
LEGACY_CONFIG = {"s_v_sampling": "uniform", "level_max": 1.0, "trained_order_share": 1.0, "parent_share": 0.0,
                 "keep_share": 1.0, "recovery_steps": 1000, "tier_finetune_steps": 0, "tier_iteration_share": 1.0,
                 "faint_share": 0.0, "tier_merge": "decimate",
                 "tier_time_cap": 0.0, "tier_hand_over": 0.0, "tier_downscale": 1, "tier_draw": "chain", "tree_steps": 0,
                 "tree_budget_steps": 0.0, "tree_spread": 2.0,
                 "tree_exit_toward_parent": 0.0, "tree_entry_toward_children": 0.0,
                 "tree_grow": None, "tree_free_roots": 0.0}
#: AdaptConfig keys removed since runs were cached: a cached run matches without them where they
#: changed nothing it drew (the chain's coarsest window and count rule, and ``tier_draw``: a run drawn
#: as a tree, or without tiers, is the same run now; a run written with ``tree_steps`` and without
#: ``tier_draw`` was drawn as a tree); a run whose tiers were drawn as a chain (``tier_draw``
#: "chain", no longer drawn) never matches
RETIRED_CONFIG = ("popping_goal", "count_mix", "tier_draw")


def adapt_cached(name: str, cfg: AdaptConfig, tag: str, *, split: str = "test", log=print) -> Path:
    """The adapted .ply of ``name`` with ``cfg``: runs ``clod-adapt``'s job into
    ``RUNS/name/tag`` (``tag + "_val"`` for ``split="val"``, trained on the fit views only:
    ``clod-adapt --holdout-val``) unless a run with the same settings is there. The C++ kernels are
    built (or loaded) before the job starts, so its ``job_seconds`` holds no one-time build.
    Returns the .ply path."""
    from clod_adapter.jobs.adapt import AdaptOptions, run

    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    holdout = split == "val"
    ply, scene, res = resolve_input(name)
    tag = tag + split_suffix(split)
    out = RUNS / name / tag
    mj = out / "metrics.json"
    if mj.is_file():
        try:
            have = json.loads(mj.read_text())
            written = have.get("config") or {}
            have_cfg = {**LEGACY_CONFIG, **written}
            if "tree_steps" in written and "tier_draw" not in written:  # written since tiers are only trees
                have_cfg["tier_draw"] = "tree"
            if have_cfg["tier_draw"] == "tree" or not have_cfg["parent_share"]:
                for k in RETIRED_CONFIG:
                    have_cfg.pop(k, None)
            if (have_cfg == json.loads(json.dumps(asdict(cfg))) and have.get("input_ply") == str(ply)
                    and bool(have.get("holdout_val", False)) == holdout):
                log(f"[{name}/{tag}] reusing {out} ({have.get('train_seconds')} s of training)")
                return out / "point_cloud.ply"
        except (OSError, ValueError):
            pass
    if out.is_dir():
        shutil.rmtree(out)  # a stale or broken run with other settings (its tiers' folders too)
    out.mkdir(parents=True)
    from clod_adapter.render import native

    native.load()  # the C++ kernels' one-time build (1-3 min on first use) is not the job's time
    log(f"[{name}/{tag}] adapting {ply.name} ({cfg.schedule}, max_sv {cfg.max_sv:g}, {cfg.iterations} steps"
        f"{', fit views only' if holdout else ''}) ...")
    run(ply, scene, out, cfg, AdaptOptions(resolution=res, progress=False, log=lambda *a: None, holdout_val=holdout))
    return out / "point_cloud.ply"


def metrics_of(ply: Path) -> dict:
    """The ``metrics.json`` of an adaptation (beside its .ply)."""
    return json.loads((Path(ply).parent / "metrics.json").read_text())


def load_input(name: str, split: str = "test"):
    """(pretrained Gaussians, scene, images of the scored views) of an input: the scored views
    are ``scene_views(scene, split)[1]`` (the test views for ``"test"``, the validation views
    for ``"val"``)."""
    ply, scene_root, res = resolve_input(name)
    scene = load_scene(scene_root, resolution=res)
    return load_model(ply), scene, [scene.load_image(c) for c in scene_views(scene, split)[1]]


def write_summary(name: str, text: str) -> Path:
    """Write a study's Markdown ``text`` to ``RUNS/name/summary.md`` atomically (the folder made
    when missing); returns the path."""
    from clod_adapter.io.atomic import atomic_write

    out = RUNS / name
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "summary.md", "w") as f:
        f.write(text if text.endswith("\n") else text + "\n")
    return out / "summary.md"


def print_summary(name: str, lines: list) -> int:
    """A study's end: its Markdown ``lines`` printed and written by :func:`write_summary` (the path
    printed after them); returns 0, the study's exit status."""
    text = "\n".join(lines)
    print(text)
    print("wrote", write_summary(name, text))
    return 0


def fmt_pct(b: float) -> str:
    return f"{100 * b:.3g} %"


def table(header: list[str], rows: list[list], align: Optional[str] = None) -> str:
    """A Markdown table."""
    al = align or ("---|" * len(header))
    out = ["| " + " | ".join(header) + " |", "|" + al]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)
