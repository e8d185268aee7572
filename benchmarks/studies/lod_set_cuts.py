"""How a LoD set's levels are cut (``clod-export --lod-meta``): the union of what each view draws
(:func:`clod_adapter.export.bake.bake`, how ``--s-v`` bakes one level) against the view-independent cut at
each Gaussian's reference distance (:func:`clod_adapter.export.bake.lod_level`, the choice), each against
splat-transform's ``--decimate`` of the input at the same count. Validation views of the default
validation adaptations (``--split val``, common.py), plain .ply levels (no SOG round trip).
Prints one line per level::

    python -m benchmarks.studies.lod_set_cuts --inputs fern skull
"""
from __future__ import annotations


from benchmarks.common import adapt_cached, load_input, run_per_input, scene_views  # noqa: E402

from clod_adapter.export.bake import bake, lod_level, lod_set_s_vs
from clod_adapter.lod.rankings import merge_decimate
from clod_adapter.lod.draw import render_lod
from clod_adapter.io.load import load_model
from clod_adapter.metrics import psnr
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.loop import reference_distances


def run_input(name: str) -> None:
    g = load_model(adapt_cached(name, AdaptConfig(), "default", split="val"))
    g0, scene, gts = load_input(name, "val")
    fit, cams = scene_views(scene, "val")
    d_ref = reference_distances(g, fit)
    score = lambda m: sum(psnr(render_lod(m, c).image.clamp(0, 1), t) for c, t in zip(cams, gts)) / len(cams)  # noqa: E731
    for s in lod_set_s_vs(g.lod.max_sv)[1:]:
        line = f"{name} s_v {s:g}:"
        for label, level in (("reference cut", lod_level(g, fit, s, d_ref=d_ref)), ("union", bake(g, fit, s_v=s))):
            dec = merge_decimate(g0, len(level), mode="decimate")
            ours, theirs = score(level), score(dec)
            line += (f" {label} {len(level):,} ({100 * len(level) / len(g):.0f} %) {ours:.2f} dB vs decimate "
                     f"{theirs:.2f} ({ours - theirs:+.2f});")
        print(line, flush=True)


def main(argv=None) -> None:
    run_per_input(__doc__, run_input, argv)


if __name__ == "__main__":
    main()
