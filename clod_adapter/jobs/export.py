"""The ``clod-export`` job: the extended .ply, a baked standard .ply for one setting, an
importance-ordered .ply, a streamed-SOG LoD set of the model's levels (through splat-transform),
a static web page drawing the continuous LoD on the GPU (PlayCanvas), optional pruning and SH
reduction, and ``export.json`` (the operations are :mod:`clod_adapter.export.bake`; the CLI,
``clod_adapter/cli/export.py``, only parses and checks flags).
Everything is computed first, then each file is written atomically."""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional

from . import check_output_dir, progress_bar

EXTENDED_NAME = "point_cloud_clod.ply"
ORDERED_NAME = "ordered.ply"
JSON_NAME = "export.json"
PREFIX_FRACTIONS = (1.0, 0.5, 0.25, 0.1)


@dataclass
class ExportOptions:
    """What ``clod-export`` writes besides the extended .ply.

    Attributes:
        s_v, budget: the level to bake (one of them, or neither: nothing baked); ``budget`` a
            count (> 1) or a fraction of the Gaussians in view.
        baked_name: the baked file's name (None: nothing baked).
        ordered: also the importance-ordered .ply (:data:`ORDERED_NAME`), prefixes scored.
        prune: drop Gaussians no training view draws at any ``s_v >= 1`` first.
        sh_max_drop_db: drop SH bands while the training-view PSNR loses at most this (None: keep).
        spz: also an .spz of every .ply (:data:`EXPORT_FORMATS`).
        lod_dir: where to write a streamed-SOG LoD set (``lod-meta.json`` + chunk folders, the
            format PlayCanvas / SuperSplat / Babylon.js stream) of the model's levels
            (:func:`clod_adapter.export.bake.lod_level` at each of :func:`clod_adapter.export.bake.lod_set_s_vs`;
            None: no set).
        sog_sh_iterations: splat-transform's ``--sh-iterations`` for the LoD set (None: its
            default, 10; :func:`clod_adapter.io.splat_transform.write_lod_set`).
        web_dir: where to write the web viewer (:func:`clod_adapter.export.web.write_web_viewer`;
            None: none).
        progress: one step per phase (a tqdm bar on a terminal, else a line per phase).
        argv: the command line recorded in ``export.json`` (None: ``sys.argv``).
    """

    s_v: Optional[float] = None
    budget: Optional[float] = None
    baked_name: Optional[str] = None
    ordered: bool = False
    prune: bool = False
    sh_max_drop_db: Optional[float] = None
    spz: bool = False
    lod_dir: Optional[Path] = None
    sog_sh_iterations: Optional[int] = None
    web_dir: Optional[Path] = None
    progress: bool = False
    argv: Optional[list] = None


def export(model, scene, train_imgs, test_cams, test_imgs, out: Path, ply: Path,
           options: Optional[ExportOptions] = None) -> dict:
    """Compute everything, then write the files (each atomically); returns the export.json dict.

    Phases, in order: the input's test PSNR, pruning, SH bands, the baked level, the importance
    order (each only when ``options`` asks for it, :func:`_reduce` and :func:`_derive`), then
    :func:`_write_files`. Every output is derived from the training views only (pruning and its
    ``d'`` anchors, SH reduction, the baked level, the importance order); the test views only
    score the results."""
    import torch

    o = options if options is not None else ExportOptions()
    t0 = time.perf_counter()
    phases = ["input PSNR"] + (["prune"] if o.prune else []) + (["SH bands"] if o.sh_max_drop_db is not None else []) \
        + (["bake"] if o.baked_name is not None else []) + (["order"] if o.ordered else []) \
        + (["LoD levels"] if o.lod_dir is not None else []) + (["web ranking"] if o.web_dir is not None else []) \
        + ["write"]
    bar = progress_bar(len(phases), "clod-export", unit="step", disable=not o.progress, every=1e-9)
    done = iter(phases)

    def step():
        bar.set_postfix_str(next(done))
        bar.update(1)

    rep: dict = {"input": str(ply), "scene": str(scene.root), "gaussians_in": len(model),
                 "sh_degree_in": model.sh_degree,
                 "train_views": len(scene.train), "test_views": [c.name for c in test_cams],
                 "resolution": [test_cams[0].width, test_cams[0].height]}
    if model.parents is not None:  # docs/method.md "Merged tiers"
        from ..lod.draw import tier_chain

        rep["tier"] = {"parents_in": sum(len(t) for t in tier_chain(model)[1:]), "tier_s_v": model.lod.tier_s_v,
                       "tier_start": model.lod.tier_start, "tiers": [len(t) for t in tier_chain(model)[1:]],
                       "drawn_by": ["extended .ply", "baked level", "web page", "LoD set"],
                       "left_out_of": ["ordered .ply (the model's own order)"],
                       "lod_set": "the model, then each tier"}
    with torch.no_grad():
        model = _reduce(model, scene, train_imgs, test_cams, test_imgs, o, rep, step)
        baked, ordered_model = _derive(model, scene, test_cams, test_imgs, o, rep, step)
        levels = _lod_levels(model, scene, test_cams, test_imgs, rep, step) if o.lod_dir is not None else None
        web = _web_inputs(model, scene, test_cams, step) if o.web_dir is not None else None
    derived = {"baked": baked, "ordered": ordered_model, "levels": levels, "web": web}
    _write_files(out, ply, model, derived, o, rep, t0)
    step()
    bar.close()
    return rep


def _reduce(model, scene, train_imgs, test_cams, test_imgs, o: ExportOptions, rep: dict, step):
    """The input's test PSNR, then pruning and SH bands as asked; returns the model to export."""
    from ..export import bake as ex
    from ..lod.draw import tier_chain
    from ..lod.tree import is_tree
    from ..evaluate.storage import ply_row_bytes

    rep["psnr_test_sv1_in"] = _mean_psnr(ex, model, test_cams, test_imgs)
    step()
    tiers = tier_chain(model)[1:]  # the parent tiers, each pruned and truncated on its own
    if o.prune:
        model, n_drop = ex.prune_never_rendered(model, scene.train, anchor_cameras=scene.train)
        rep["prune"] = {"dropped": n_drop, "kept": len(model),
                        "bytes_saved": n_drop * ply_row_bytes(model),
                        "psnr_test_sv1_after": _mean_psnr(ex, model, test_cams, test_imgs)}
        if tiers and not is_tree(model):  # each tier's own never-drawn rows (their d' anchors kept)
            pruned = [ex.prune_never_rendered(t, scene.train, anchor_cameras=scene.train) for t in tiers]
            tiers = [replace(t, lod=orig.lod) for (t, _), orig in zip(pruned, tiers)]
            rep["prune"]["parents_dropped"] = sum(n for _, n in pruned)
        step()
    if o.sh_max_drop_db is not None:
        model, info = ex.reduce_sh(model, scene.train, train_imgs, o.sh_max_drop_db)
        info["psnr_test_sv1_after"] = _mean_psnr(ex, model, test_cams, test_imgs)
        rep["sh"] = info
        step()
    if tiers:  # the tiers follow the model (same SH degree, docs/method.md "Merged tiers")
        above = None
        for t in reversed(tiers):
            above = replace(ex.truncate_sh(t, model.sh_degree), parents=above)
        model = replace(model, parents=above)
        rep["tier"]["parents_out"] = sum(len(t) for t in tiers)
    rep["gaussians_out"] = len(model)
    rep["sh_degree_out"] = model.sh_degree
    return model


def _derive(model, scene, test_cams, test_imgs, o: ExportOptions, rep: dict, step):
    """The baked level and the importance-ordered model as asked: (baked or None, ordered or None)."""
    from ..export import bake as ex
    from ..lod.budget import as_budget
    from ..lod.draw import PAPER
    from ..lod.tree import own_model
    from ..metrics import psnr

    baked = None
    if o.baked_name is not None:
        baked, binfo = ex.bake(model, scene.train, s_v=o.s_v, budget=as_budget(o.budget), return_info=True)
        lod_ps = [psnr(ex.render_lod(model, c, o.s_v, budget=as_budget(o.budget), eta_grad=PAPER).image, gt, cap=True)
                  for c, gt in zip(test_cams, test_imgs)]
        bk_ps = [psnr(ex.render_lod(baked, c).image, gt, cap=True) for c, gt in zip(test_cams, test_imgs)]
        rep["baked"] = {"file": o.baked_name, "s_v": o.s_v, "budget": o.budget, "cameras": "train",
                        "gaussians": len(baked), "of_them_parents": binfo.n_parents, "mean_rendered_per_view_lod": binfo.per_view_rendered,
                        "opacity": binfo.chosen, "psnr_vs_render_lod_train_views": binfo.psnr_vs_lod,
                        "psnr_test_render_lod": sum(lod_ps) / len(lod_ps),
                        "psnr_test_baked": sum(bk_ps) / len(bk_ps)}
        step()
    ordered_model = None
    if o.ordered:  # a merge tree's own Gaussians (tier 0) as a model without tiers
        model = own_model(model)
        persist = ex.persistence(model, scene.train)
        perm = ex.importance_order(model, scene.train, persist=persist)
        ordered_model = model.subset(perm)
        rep["ordered"] = {"file": ORDERED_NAME, "order_views": "train", "persistence_zero": int((persist == 0).sum()),
                          "prefix_vs_selection_test": ex.prefix_vs_selection(model, perm, test_cams, test_imgs,
                                                                             PREFIX_FRACTIONS)}
        step()
    return baked, ordered_model


def _lod_levels(model, scene, test_cams, test_imgs, rep: dict, step) -> list:
    """The LoD set's levels (:func:`clod_adapter.export.bake.lod_set_levels`: a merge tree's own
    cut at each node's reference distance, as many nodes per level as each merged tier; else the
    model cut at each of :func:`clod_adapter.export.bake.lod_set_s_vs`; reference distances from
    the training views), finest first, each scored on the test views as a plain model;
    ``rep["lod_meta"]`` says how they were cut. Returns the levels."""
    from ..export import bake as ex
    from ..metrics import psnr

    tree = model.lod is not None and model.lod.tree
    levels, rows = [], []
    for k, (g, s) in enumerate(ex.lod_set_levels(model, scene.train)):
        ps = [psnr(ex.render_lod(g, c).image, gt, cap=True) for c, gt in zip(test_cams, test_imgs)]
        levels.append(g)
        rows.append({"level": k, "s_v": s, "gaussians": len(g), "psnr_test": sum(ps) / len(ps)})
    rep["lod_meta"] = {"levels": rows, "tool": "splat-transform",
                       "cut": "the merge tree's cut at each node's reference distance, a merged tier's count per "
                              "level" if tree else "critical s_v at the reference distance (training views)"}
    step()
    return levels


def _web_inputs(model, scene, test_cams, step) -> dict:
    """What the web page needs besides the model: its cameras (the test views, then the
    training views) and the static cut's ranking (LightGaussian significance on the training
    views, :func:`clod_adapter.lod.rankings.lightgaussian_significance`; None for a merge tree, whose
    page has no static cut)."""
    from ..lod.rankings import lightgaussian_significance
    from ..lod.tree import is_tree

    scores = None if is_tree(model) else lightgaussian_significance(model.with_sigma_d(None), scene.train)
    step()
    test_names = {c.name for c in test_cams}
    return {"cameras": list(test_cams) + [c for c in scene.train if c.name not in test_names], "scores": scores}


def _write_web(model, web_dir: Path, web: dict, rep: dict) -> list[str]:
    """The web viewer (:func:`clod_adapter.export.web.write_web_viewer`) into ``web_dir``;
    ``rep["web"]`` says what was written. Returns the names written."""
    from ..export.web import PLAYCANVAS_VERSION, write_web_viewer

    names = write_web_viewer(model, web_dir, web["cameras"], web["scores"])
    static = "lightgaussian significance (training views)" if web["scores"] is not None else None  # a tree: none
    rep["web"] = {"dir": str(web_dir), "files": names, "engine": f"playcanvas {PLAYCANVAS_VERSION}",
                  "cameras": len(web["cameras"]), "static_cut": static,
                  "open": f"cd {web_dir} && python -m http.server, then http://localhost:8000/"}
    return names


def _write_lod_set(levels: list, lod_dir: Path, rep: dict, sh_iterations: Optional[int]) -> None:
    """The levels as plain .ply files in a scratch folder, then splat-transform's LoD set in
    ``lod_dir`` (:func:`clod_adapter.io.splat_transform.write_lod_set`); ``rep["lod_meta"]`` gets
    the folder, the names written and what the tool reads back."""
    import tempfile

    from ..io.ply import write_ply
    from ..io.splat_transform import SPLAT_TRANSFORM_VERSION, write_lod_set

    with tempfile.TemporaryDirectory(prefix="clod-lod-") as tmp:
        plys = [write_ply(Path(tmp) / f"lod{k}.ply", g) for k, g in enumerate(levels)]
        info, names = write_lod_set(plys, lod_dir, overwrite=True, sh_iterations=sh_iterations)
    rep["lod_meta"].update({"dir": str(lod_dir), "files": names, "info": info,
                            "tool_version": SPLAT_TRANSFORM_VERSION})


def _write_files(out: Path, ply: Path, model, derived: dict, o: ExportOptions, rep: dict, t0: float) -> None:
    """The export's files, each atomically: the extended .ply, the baked level, the ordered .ply
    (``derived``), their .spz copies, the LoD set (its chunk folders, then
    ``lod-meta.json``), the web viewer, then ``export.json`` (``rep``, completed here with bytes
    and files)."""
    from ..io.atomic import atomic_write

    check_output_dir(out, [ply], force=True)  # checked before; create it now
    models = [(EXTENDED_NAME, model), (o.baked_name, derived["baked"]), (ORDERED_NAME, derived["ordered"])]
    files = []
    for fmt in ("ply",) + (("spz",) if o.spz else ()):
        for name, m in models:
            if m is not None:
                files.append(EXPORT_FORMATS[fmt].write(out / Path(name).with_suffix(EXPORT_FORMATS[fmt].suffix).name,
                                                       m))
    if derived["levels"] is not None:
        _write_lod_set(derived["levels"], o.lod_dir, rep, o.sog_sh_iterations)
        if Path(o.lod_dir).resolve() == out.resolve():
            files += rep["lod_meta"]["files"]
    if derived["web"] is not None:
        names = _write_web(model, o.web_dir, derived["web"], rep)
        if Path(o.web_dir).resolve() == out.resolve():
            files += names
    rep["bytes"] = {"input": ply.stat().st_size, **{f: _bytes(out / f) for f in files}}
    rep["seconds"] = round(time.perf_counter() - t0, 2)
    rep["command"] = "clod-export " + " ".join(sys.argv[1:] if o.argv is None else o.argv)
    files.append(JSON_NAME)
    rep["files"] = files
    with atomic_write(out / JSON_NAME, "w") as f:
        json.dump(rep, f, indent=2)
        f.write("\n")


def write_ply_file(path: Path, model) -> str:
    """:func:`clod_adapter.io.ply.write_ply` (atomic; the extended INRIA layout); returns the file name."""
    from ..io.ply import write_ply

    write_ply(path, model)
    return path.name


@dataclass(frozen=True)
class ExportFormat:
    """One file format ``clod-export`` writes: its suffix, its writer (``write(path, model) ->
    file name``, atomic) and what it holds. Adding a format is one entry of
    :data:`EXPORT_FORMATS` (and its round trip in ``tests/test_export.py``)."""

    suffix: str
    write: Callable
    what: str


def write_spz(path: Path, model) -> str:
    """Write ``model`` (``sigma_d`` dropped: SPZ has no extra attributes) as .spz with gsply
    (``gsply.write_spz``, SPZ version 3, 12 fractional bits), atomically; returns the file name.

    The plain INRIA .ply goes through ``gsply.plyread`` so gsply's own conventions (log scales,
    logit opacities) are used."""
    import os
    import tempfile

    import gsply

    from ..io.ply import write_ply

    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".spz-") as d:
        plain = write_ply(Path(d) / "plain.ply", model.with_sigma_d(None))
        tmp = Path(d) / path.name
        gsply.write_spz(tmp, gsply.plyread(plain))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    return path.name


def _bytes(path: Path) -> int:
    """Size of a file, or of every file under a folder (a LoD set's chunk folder)."""
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _mean_psnr(ex, model, cams, imgs) -> float:
    from ..metrics import psnr

    ps = [psnr(ex.render_lod(model, c, 1.0).image, gt, cap=True) for c, gt in zip(cams, imgs)]
    return sum(ps) / len(ps)


def summary(rep: dict) -> str:
    lines = [f"{rep['gaussians_in']:,} -> {rep['gaussians_out']:,} Gaussians, SH degree {rep['sh_degree_in']} -> "
             f"{rep['sh_degree_out']}; test PSNR of the input at s_v = 1: {rep['psnr_test_sv1_in']:.2f} dB"]
    if "prune" in rep:
        p = rep["prune"]
        lines.append(f"prune: dropped {p['dropped']} ({p['bytes_saved']} bytes), test PSNR s_v=1 {p['psnr_test_sv1_after']:.2f} dB")
    if "sh" in rep:
        s = rep["sh"]
        lines.append(f"SH: degree {s['degree_in']} -> {s['degree_out']}, {s['bytes_saved']} bytes saved, "
                     f"train PSNR cost {s['psnr_cost_db']:.3f} dB")
    if "baked" in rep:
        b = rep["baked"]
        lines.append(f"baked: {b['gaussians']} Gaussians, opacity {b['opacity']}, test PSNR {b['psnr_test_baked']:.2f} "
                     f"(render_lod {b['psnr_test_render_lod']:.2f})")
    if "lod_meta" in rep:
        for r in rep["lod_meta"]["levels"]:
            at = f"s_v = {r['s_v']:g}" if r["s_v"] is not None else f"tier {r['level']} whole"
            lines.append(f"LoD set level {r['level']} ({at}): {r['gaussians']:,} Gaussians, "
                         f"test PSNR {r['psnr_test']:.2f} dB")
        if "dir" in rep["lod_meta"]:
            lines.append(f"LoD set: {Path(rep['lod_meta']['dir']) / 'lod-meta.json'} (splat-transform reads "
                         f"{rep['lod_meta']['info'].get('lodCounts')} per level)")
    if "web" in rep:
        lines.append(f"web viewer: {rep['web']['open']}")
    if "ordered" in rep:
        for r in rep["ordered"]["prefix_vs_selection_test"]:
            lines.append(f"prefix {r['fraction']:.0%} ({r['count']}): {r['psnr_prefix']:.2f} dB vs selection "
                         f"{r['psnr_selection']:.2f} dB ({r['rendered_per_view']:.0f} per view)")
    return "\n".join("clod-export: " + s for s in lines)


#: the formats clod-export writes, by name (``--spz`` adds ``spz`` to ``ply``).
EXPORT_FORMATS = {
    "ply": ExportFormat(".ply", write_ply_file, "INRIA .ply (+ sigma_d and the level gains for the extended file)"),
    "spz": ExportFormat(".spz", write_spz, "SPZ v3 via gsply (sigma_d dropped)"),
}
