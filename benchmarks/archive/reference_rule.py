"""``render_lod`` against ``docs/lod_rule.md`` on the real scenes: each input's default adaptation
(cached, common.py) drawn from every test view at ``s_v`` 1 ... 30 by the library
(:func:`clod_adapter.lod.draw.lod_subset`: the model's Gaussians and, past its ``tier_s_v``, its
parent tier) and by the page's numpy implementation (``examples/reference_lod.py``
``draw_tiered``, which reads the .ply itself). Prints the Gaussians (and parents) drawn by one and
not the other and the largest opacity difference; exits 1 when a single one differs::

    python -m benchmarks.archive.reference_rule                 # fern, skull

Archived 2026-11-26: it draws the file with ``examples/reference_lod_chain.py``'s ``draw_tiered``
(the cross-fade chain), removed; the merge tree is held to ``examples/reference_lod.py`` by
``tests/test_tree.py``, a model without tiers to ``examples/reference_lod_plain.py`` by
``tests/test_reference_lod.py``. It runs at commit 207ff0d.
"""
from __future__ import annotations

import sys

from benchmarks.common import adapt_cached, load_input, parse_inputs_args, scene_views  # noqa: E402

import numpy as np
import torch

from clod_adapter.lod.draw import lod_subset
from clod_adapter.io.load import load_model
from clod_adapter.train.config import AdaptConfig

from examples import reference_lod_chain as ref

S_VS = (1.0, 1.05, 1.2, 1.5, 2.0, 3.0, 5.0, 10.0, 30.0)


def run_input(name: str, split: str) -> int:
    ply = adapt_cached(name, AdaptConfig(), "default", split=split)
    g, m = load_model(ply), ref.read_model(ply)
    _, scene, _ = load_input(name, split)
    differ = drawn = drawn_p = 0
    max_op = 0.0
    empty = np.zeros(0, np.int64)
    for cam in scene_views(scene, split)[1]:
        for s in S_VS:
            sub = lod_subset(g, cam, s)
            out = ref.draw_tiered(m, cam.viewmat.double().numpy(), cam.K.double().numpy(), cam.width, cam.height, s)
            a = sub.indices.numpy()
            b = out["model"]["ids"] if out["model"] is not None else empty
            ap = sub.parent_indices.numpy() if sub.parent_indices is not None else empty
            bp = out["parents"]["ids"] if out["parents"] is not None else empty
            differ += np.setxor1d(a, b).size + np.setxor1d(ap, bp).size
            drawn += a.size
            drawn_p += ap.size
            if np.array_equal(a, b) and np.array_equal(ap, bp) and a.size + ap.size:
                ops = np.concatenate([o["opacities"] for o in (out["model"], out["parents"]) if o is not None])
                max_op = max(max_op, float(np.abs(sub.opacities.numpy() - ops).max()))
    tier = f", tier from s_v = {g.lod.tier_s_v:g}" if g.parents is not None else ", no tier"
    print(f"[{name}] {drawn:,} Gaussians and {drawn_p:,} parents drawn over the {split} views x {len(S_VS)} "
          f"s_v{tier}: {differ} differ; largest opacity difference {max_op:.1e}")
    return differ


def main() -> int:
    a = parse_inputs_args(__doc__)
    with torch.no_grad():
        bad = sum(run_input(name, a.split) for name in a.inputs)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
