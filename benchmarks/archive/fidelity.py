"""Fidelity to the input: the equal-time comparison scored against the input's own renders.

On a well-fitted capture the input's render is close to the photograph, so how far a level of
detail strays from the input is most of its error there. The shared checkpoints score 24-27 dB on
views they never saw, and there a level that strays from the input can score higher than one that
keeps it; this study takes the photographs out. On the validation views of each input's default
validation adaptation (``--split val``, common.py; adapted when not cached), the comparison of
``benchmarks/quality_vs_time.py`` (:func:`clod_adapter.evaluate.comparison.compare`: the adapted model
along ``s_v`` and at budgets, LightGaussian and opacity cuts, splat-transform 3.7.0's ``--decimate``
and ``--decimate-adaptive``, every setting timed in the same interleaved rounds, CPU rasteriser) is
scored with the input's own render of each view as the image (PSNR in dB; the input itself is
exact). Prints, per input, the best PSNR within each share of the input's frame time for the
adapted model, the better decimator and the better cut, and every point by time::

    python -m benchmarks.archive.fidelity --inputs skull fern
"""
from __future__ import annotations


from benchmarks.common import adapt_cached, load_input, run_per_input, scene_views  # noqa: E402

import torch

from clod_adapter.evaluate import comparison as qvt
from clod_adapter.lod.rankings import render_subset
from clod_adapter.evaluate.frontier import Point, best_within
from clod_adapter.io.load import load_model
from clod_adapter.io.splat_transform import find_splat_transform
from clod_adapter.train.config import AdaptConfig

SHARES = (0.95, 0.9, 0.8, 0.7, 0.6, 0.5, 0.45, 0.4, 0.35, 0.3, 0.25)
ROUNDS = 3
GROUPS = {"adapted": ("clod",), "decimator": ("decimate", "decimate_adaptive"), "cut": ("lightgaussian", "opacity")}


def run_input(name: str) -> None:
    tool = find_splat_transform()
    if tool is None:
        raise SystemExit("fidelity.py: splat-transform not found (npm install @playcanvas/splat-transform@3.7.0)")
    cfg = AdaptConfig()
    ply = adapt_cached(name, cfg, "default", split="val")
    g0, scene, _ = load_input(name, "val")
    fit, cams = scene_views(scene, "val")
    everything = torch.arange(len(g0))
    refs = [render_subset(g0, c, everything).image.clamp(0, 1) for c in cams]
    comp = qvt.compare(load_model(ply), g0, fit, cams, refs, max_sv=cfg.max_sv,
                       options=qvt.CompareOptions(merge_tool=tool, repeats=ROUNDS, full_rounds=0),
                       log=lambda s: print(f"[{name}] {s}", flush=True))
    base = next(s for s in comp.settings if s.method == "input").ms
    # the equal-time table: equal-count settings ("match:...") left out; Point.ms holds the share of the input's frame
    points = [Point(s.method, s.setting, s.ms / base, s.psnr, sum(s.drawn) / max(len(s.drawn), 1))
              for s in comp.settings if not s.setting.startswith("match")]
    print(f"\n{name}: PSNR against the input's render, {len(cams)} validation views, best within each share of "
          f"the input's frame ({ROUNDS} interleaved rounds)\n")
    print("| within | " + " | ".join(GROUPS) + " |\n|---|" + "---|" * len(GROUPS))
    for share in SHARES:
        cells = [best_within([p for p in points if p.method in m], share) for m in GROUPS.values()]
        print(f"| {100 * share:.0f} % | " + " | ".join(
            f"{c.psnr:.2f} ({c.method} {c.setting}, {100 * c.ms:.0f} %)" if c else "-" for c in cells) + " |")
    print(f"\n{name}: every point by time share (PSNR against the input's render, drawn per view)")
    for p in sorted(points, key=lambda p: -p.ms):
        print(f"  {100 * p.ms:5.0f} %  {p.psnr:6.2f}  {p.method:18s} {p.setting:20s} {p.drawn:9.0f}", flush=True)


def main(argv=None) -> None:
    run_per_input(__doc__, run_input, argv, inputs=("skull", "fern"))


if __name__ == "__main__":
    main()
