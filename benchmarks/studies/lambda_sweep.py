"""lambda_reg against quality at full detail and depth of the LoD (default: fern).

Fine-tunes the pretrained model of each input (``--inputs``; ``--input NAME=PLY:SCENE[:RES]``
for any checkpoint) once per setting (default seed, other settings default)
and prints PSNR and the rendered fraction at s_v = 1, 2, 3, 5 on the scored views: with
``--split val`` (the default: lambda_reg is a choice) trained on the training views minus the
validation views and scored on those (:func:`clod_adapter.io.scene.validation_split`), with
``--split test`` trained on every training view and scored on the test views. The table of
"``lambda_reg = 0.05``" (docs/studies.md) was measured on the validation views:

    python -m benchmarks.studies.lambda_sweep 1:500 0.1:500 0.01:500 0.03:1000 0.05:1000

(LAMBDA:STEPS per run; 2.5-5 min each on 2 cores).
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")

import torch  # noqa: E402


from benchmarks.common import add_inputs_args, add_split_arg, resolve_input, scene_views, selected_inputs  # noqa: E402

from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.loop import fit, prepare  # noqa: E402
from clod_adapter.evaluate.level_metrics import evaluate_level  # noqa: E402
from clod_adapter.io.load import load_model, load_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LAMBDA:STEPS, e.g. 0.05:1000 (before --inputs, which takes several names)")
    add_inputs_args(ap, ["fern"])
    add_split_arg(ap, "val")
    args = ap.parse_args()
    torch.set_num_threads(2)
    for name in selected_inputs(args):
        sweep(name, args.runs, args.split)


def sweep(name: str, runs: list, split: str) -> None:
    """Fine-tune ``name``'s pretrained model once per LAMBDA:STEPS of ``runs`` and print a row each."""
    ply, root, res = resolve_input(name)
    g = load_model(ply)
    sc = load_scene(root, resolution=res)
    fit_cams, ev = scene_views(sc, split)
    tr = [sc.load_image(c) for c in fit_cams]
    te = [sc.load_image(c) for c in ev]
    print(f"{name}: {len(fit_cams)} fit views, scored on {len(ev)} {'validation' if split == 'val' else 'test'} views")
    print(f"{'lambda':>8} {'steps':>6} " + " ".join(f"{'s_v=' + str(s):>15}" for s in (1, 2, 3, 5)) + "  seconds")
    for spec in runs:
        lam, steps = spec.split(":")
        cfg = AdaptConfig(schedule="paper", lambda_reg=float(lam), iterations=int(steps))
        t = time.perf_counter()
        st = prepare(g, fit_cams, cfg, tr)
        fit(st, fit_cams, tr, cfg, progress=False)
        m = st.gaussians().detach()
        lv = [evaluate_level(m, ev, te, float(s)) for s in (1, 2, 3, 5)]
        cells = " ".join(f"{r.psnr:6.2f}dB {100 * r.fraction:4.0f}%" for r in lv)
        print(f"{float(lam):8g} {int(steps):6d} {cells}  {time.perf_counter() - t:.0f}", flush=True)


if __name__ == "__main__":
    main()
