"""What the LoD path adds to a frame: an ``s_v`` frame of the adapted model against a static model
made of exactly what that frame draws.

For each input (default: skull and fern, their cached default adaptations, common.py) and each
``s_v``, every evaluation view gets a plain model holding the Gaussians ``render_lod(g, cam, s_v)``
hands the rasteriser, with the attributes it draws them with (:func:`clod_adapter.lod.draw.lod_subset`:
level scales and colours, faded opacities). The two render the same image (checked: largest
|difference| printed) and differ only in the per-frame LoD work: the frustum and ``d'`` over all N
Gaussians, Eq. 2's mask, the kept indices and counts, the level gains and the fade. The two of
one view are timed back to back (whole ``render_lod`` frames, CPU rasteriser, 2 threads), in
alternating order over the rounds after a warm-up round, so the machine's drift cancels in each
pair; the overhead is the median over views and rounds of
(LoD - static), read as a share of the input's frame (the median of its frames)::

    python -m benchmarks.studies.lod_overhead                    # skull, fern; test views
    python -m benchmarks.studies.lod_overhead --inputs skull --s-v 10 20

Goal (exit 1 when missed): the overhead at most 3 % of the input's frame at every ``s_v``. The
model's parent tier, where it has one, is left out: this is the cost of the rule over the model's
own Gaussians.
"""
from __future__ import annotations

import statistics
import sys
import time
from dataclasses import replace

from benchmarks.common import adapt_cached, load_input, parse_inputs_args, scene_views  # noqa: E402

import torch

from clod_adapter.lod.draw import lod_subset, render_lod
from clod_adapter.gaussians import Gaussians
from clod_adapter.io.load import load_model
from clod_adapter.train.config import AdaptConfig

GOAL_SHARE = 0.03


def drawn_model(g, cam, s_v) -> Gaussians:
    """A plain model of what ``render_lod(g, cam, s_v)`` draws, with the attributes it draws."""
    sub = lod_subset(g, cam, s_v)
    op = sub.opacities.clamp(1e-7, 1 - 1e-7)
    return Gaussians(sub.means.contiguous(), sub.quats.contiguous(), sub.scales.log().contiguous(),
                     torch.logit(op).contiguous(), sub.colors[:, :1].contiguous(), sub.colors[:, 1:].contiguous())


def _ms(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def run_input(name: str, split: str, s_vs: list, repeats: int) -> bool:
    g0, scene, _ = load_input(name, split)
    _, cams = scene_views(scene, split)
    # the model's own LoD path: a parent tier (drawn from its tier_s_v on) is left out here
    g = replace(load_model(adapt_cached(name, AdaptConfig(), "default", split=split)), parents=None)
    ok = True
    with torch.no_grad():
        ms_in = statistics.median(_ms(lambda: render_lod(g0, c)) for _ in range(repeats) for c in cams)
        print(f"[{name}] input {ms_in:.1f} ms per frame ({len(cams)} {split} views, {repeats} rounds)")
        for s in s_vs:
            statics = [drawn_model(g, c, s) for c in cams]
            diff = max(float((render_lod(g, c, s).image - render_lod(m, c).image).abs().max())
                       for m, c in zip(statics, cams))
            pairs = []  # (LoD, static) of one view back to back, the order alternating per round
            for r in range(repeats + 1):
                for m, c in zip(statics, cams):
                    a, b = (lambda: render_lod(g, c, s)), (lambda: render_lod(m, c))
                    ta, tb = (_ms(a), _ms(b)) if r % 2 else tuple(reversed((_ms(b), _ms(a))))
                    if r:  # round 0 warms up
                        pairs.append((ta, tb))
            over = statistics.median(a - b for a, b in pairs)
            share = over / ms_in
            ok &= share <= GOAL_SHARE
            print(f"[{name}] s_v = {s:<5g} {statistics.mean(len(m) for m in statics):8,.0f} drawn: LoD "
                  f"{statistics.median(a for a, _ in pairs):6.2f} ms, the same set as a static model "
                  f"{statistics.median(b for _, b in pairs):6.2f} ms, overhead {over:+.2f} ms = {100 * share:+.1f} % of "
                  f"the input's frame ({'ok' if share <= GOAL_SHARE else 'MISS'}, goal <= {100 * GOAL_SHARE:g} %); "
                  f"images differ by <= {diff:.1e}")
    return ok


def main() -> int:
    a = parse_inputs_args(__doc__, inputs=("skull", "fern"), split="test", extra=[
        ("--s-v", {"type": float, "nargs": "+", "default": [2.0, 5.0, 10.0, 20.0, 30.0], "help": "levels"}),
        ("--repeats", {"type": int, "default": 9, "help": "interleaved timing rounds"})])
    ok = True
    for name in a.inputs:
        ok &= run_input(name, a.split, a.s_v, a.repeats)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
