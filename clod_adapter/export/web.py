"""``clod-export --web``: a static page drawing the continuous LoD per frame on the GPU with the
PlayCanvas engine (npm ``playcanvas``, pinned to :data:`PLAYCANVAS_VERSION` by the root
``package.json``, installed by ``npm ci``; copied into the export, never fetched from a CDN).
The page is ``web_page/`` (``index.html``, ``clod.mjs``: the LoD rule of :mod:`clod_adapter.lod.rule`
as a PlayCanvas work-buffer modifier; ``clod_tree.mjs``: the merge tree's rule of
``docs/lod_rule.md``, ported from ``examples/reference_lod.py``); :func:`write_web_viewer` adds
the engine, the model and its per-splat LoD data.

Conventions (PlayCanvas 2.x): a camera looks down its -Z axis with +Y up (OpenGL); ours
(gsplat ``viewmats``, COLMAP) look down +Z with +Y down (OpenCV). The same world frame is kept
(the splat entity is not rotated), so a camera-to-world rotation ``R_cv`` becomes
``R_cv diag(1, -1, -1)``. PlayCanvas's ``fov`` is vertical, in degrees; the page replaces the
engine's projection by each view's pinhole ``K`` when the canvas has the view's size.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

__all__ = ["PLAYCANVAS_VERSION", "find_playcanvas", "playcanvas_pose", "web_streams", "tree_streams", "write_web_viewer"]

#: the pinned engine (root ``package.json``).
PLAYCANVAS_VERSION = "2.23.3"
#: the engine build copied into exports (ES module, minified).
ENGINE_FILE = "playcanvas.min.mjs"


def find_playcanvas() -> Optional[Path]:
    """``node_modules/playcanvas/build/playcanvas.min.mjs`` under the project root or the current
    directory (where ``npm ci`` installs it), or None."""
    from ..io.splat_transform import project_root

    for folder in (project_root(), Path.cwd()):
        if folder is not None:
            p = folder / "node_modules" / "playcanvas" / "build" / ENGINE_FILE
            if p.is_file():
                return p
    return None


def playcanvas_pose(camera) -> dict:
    """One of our cameras (``viewmat``, ``K``, ``width``, ``height``) in PlayCanvas's terms: its
    OpenCV pose (:func:`clod_adapter.io.camera_pose.camera_to_world`, ``q_cv`` wxyz) turned
    half a turn about its own x axis, ``q_cv (0, 1, 0, 0)``.

    Returns:
        ``{"position": [x, y, z] (world units), "rotation": [x, y, z, w] (unit quaternion,
        PlayCanvas ``Quat`` order), "fov": vertical field of view in degrees, "K": [fx, fy, cx, cy]
        (pixels; the page projects with them when its canvas has the camera's size)}``.
    """
    from ..io.camera_pose import camera_to_world, matrix_to_quat

    R_wc, position, fov = camera_to_world(camera)
    w, x, y, z = (float(v) for v in matrix_to_quat(R_wc))
    K = camera.K
    return {"position": [float(v) for v in position], "rotation": [w, z, -y, -x],
            "fov": math.degrees(fov), "K": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]}


#: the per-splat streams of ``clod.bin``, in order (each [N] float32).
WEB_STREAMS = ("x", "y", "z", "sigma_d", "opacity_logit", "opacity_gain", "scale_gain", "f_dc_gain_0",
               "f_dc_gain_1", "f_dc_gain_2", "static_rank")
#: the per-node streams of a merge tree's ``clod.bin`` (:func:`tree_streams`), in order.
TREE_STREAMS = ("x", "y", "z", "sigma_d", "exit", "d_ref", "parent", "opacity_logit", "scale_0", "scale_1", "scale_2")
#: the page's files (``web_page/`` in this package) and what ``clod-export --web`` adds beside them.
PAGE_FILES = ("index.html", "clod.mjs", "clod_tree.mjs")
MODEL_NAME, DATA_NAME, CONFIG_NAME = "model.ply", "clod.bin", "clod.json"


def web_streams(model, static_scores) -> dict:
    """The per-splat data the page's shader reads (:data:`WEB_STREAMS`), [N] float32 numpy each:
    the centres (the page's frustum and normaliser), the raw ``sigma_d`` and opacity logit, the
    level gains (0 where the model has none) and each splat's rank in ``static_scores`` [N]
    (0 = kept first; the page's static cut of the same count)."""
    import numpy as np
    import torch

    n = len(model)
    zero = torch.zeros(n)
    rank = torch.empty(n, dtype=torch.float32)
    rank[torch.sort(-static_scores.detach().double().cpu(), stable=True).indices] = torch.arange(n, dtype=torch.float32)
    sh0g = model.sh0_gain.reshape(n, 3) if model.sh0_gain is not None else torch.zeros(n, 3)
    cols = {"x": model.means[:, 0], "y": model.means[:, 1], "z": model.means[:, 2], "sigma_d": model.sigma_d,
            "opacity_logit": model.opacity_logits,
            "opacity_gain": model.opacity_logit_gain if model.opacity_logit_gain is not None else zero,
            "scale_gain": model.log_scale_gain if model.log_scale_gain is not None else zero,
            "f_dc_gain_0": sh0g[:, 0], "f_dc_gain_1": sh0g[:, 1], "f_dc_gain_2": sh0g[:, 2], "static_rank": rank}
    return {k: np.ascontiguousarray(cols[k].detach().float().cpu().numpy()) for k in WEB_STREAMS}


def tree_streams(model) -> tuple[dict, list[int]]:
    """The per-node data a merge tree's page reads (:data:`TREE_STREAMS`, [N_0 + N_1 + ...]
    float32 numpy each, tier 0's rows first, each tier's rows in the file's order): the centres,
    ``sigma_d``, the exit (+inf: a parent's lead), the reference distance, the parent's row in
    that order (-1 in the last tier), the opacity logit and the log-scales; and the tiers' counts.

    Raises:
        ValueError: a node index past float32's exact integers (2^24 nodes).
    """
    import numpy as np
    import torch

    from ..lod import tree

    ts = tree.tiers_of(model)
    counts = [len(t) for t in ts]
    if sum(counts) > 2 ** 24:
        raise ValueError(f"write_web_viewer: a tree of {sum(counts):,} nodes; the page indexes at most 2^24")
    off = np.cumsum([0] + counts)
    cols = {k: [] for k in TREE_STREAMS}
    for k, t in enumerate(ts):
        parent = (t.extra[tree.PARENT_KEY].long() + int(off[k + 1])) if k + 1 < len(ts) else torch.full((len(t),), -1)
        for name, v in (("x", t.means[:, 0]), ("y", t.means[:, 1]), ("z", t.means[:, 2]), ("sigma_d", t.sigma_d),
                        ("exit", t.extra[tree.EXIT_KEY]), ("d_ref", t.extra[tree.REFERENCE_KEY]),
                        ("parent", parent), ("opacity_logit", t.opacity_logits),
                        ("scale_0", t.log_scales[:, 0]), ("scale_1", t.log_scales[:, 1]),
                        ("scale_2", t.log_scales[:, 2])):
            cols[name].append(v.detach().float().cpu().numpy())
    return {k: np.ascontiguousarray(np.concatenate(v)) for k, v in cols.items()}, counts


def write_web_viewer(model, out_dir: Path, cameras, static_scores, *, engine: Optional[Path] = None) -> list[str]:
    """A self-contained static page that draws ``model``'s continuous LoD on the GPU with the
    PlayCanvas engine: the page (:data:`PAGE_FILES`), the engine (copied from npm's
    ``node_modules``), the model's base attributes as a standard ``model.ply``, the per-splat
    LoD data ``clod.bin`` (:func:`web_streams`) and ``clod.json`` (counts, the LoD settings,
    ``cameras`` as PlayCanvas poses). A merge tree (:func:`clod_adapter.lod.tree.is_tree`)
    is written as one set: ``model.ply`` holds every tier's nodes (tier 0's first),
    ``clod.bin`` their :func:`tree_streams` and ``clod.json`` a ``"tree"`` entry (the tiers'
    ``counts`` and the slider's top ``sv_max``, 1.2 times the last tier's ``max_sv`` at the model's
    ``s_v``); the page draws the cut of ``docs/lod_rule.md`` at its ``s_v`` or within a count
    budget, as :func:`clod_adapter.lod.draw.render_lod` does. Merged tiers not linked into a tree
    are not drawn, so not written. Each file is written atomically.

    Args:
        model: an adapted :class:`clod_adapter.gaussians.Gaussians` (``sigma_d`` required),
            with or without a merge tree.
        out_dir: the folder (created when missing).
        cameras: the poses the page offers (e.g. the scene's test and training cameras).
        static_scores: [N] the ranking of the page's static cut (higher = kept first); not read
            for a merge tree (None there).
        engine: the engine file (default :func:`find_playcanvas`).

    Returns:
        the names written into ``out_dir``.

    Raises:
        FileNotFoundError: no engine (``npm ci`` installs it).
        ValueError: the model (or a tier of its tree) has no ``sigma_d``.
    """
    import json
    import shutil
    from dataclasses import replace
    from importlib import resources

    from ..lod import tree as tree_mod
    from ..gaussians import concat
    from ..io.atomic import atomic_write
    from ..io.ply import write_ply
    from ..lod_settings import FADE_RAMP_S_V, LodSettings

    if model.sigma_d is None:
        raise ValueError("write_web_viewer: the model has no sigma_d (run clod-adapt first)")
    engine = engine or find_playcanvas()
    if engine is None:
        raise FileNotFoundError("PlayCanvas engine not found: run `npm ci` in the repository root")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    m = model.detach().to("cpu")
    is_tree = tree_mod.is_tree(m)
    if is_tree and any(t.sigma_d is None for t in tree_mod.tiers_of(m)):
        raise ValueError("write_web_viewer: a tier of the tree has no sigma_d")
    cams = [{"name": getattr(c, "name", f"view{i}"), "width": int(c.width), "height": int(c.height),
             **playcanvas_pose(c), "viewmat": [float(v) for v in c.viewmat.reshape(-1)]} for i, c in enumerate(cameras)]
    if is_tree:  # every tier's nodes as one set: the rows of model.ply and clod.bin
        ts = tree_mod.tiers_of(m)
        write_ply(out_dir / MODEL_NAME, concat([replace(t.with_sigma_d(None), extra={}) for t in ts]))
        streams, counts = tree_streams(m)
        with atomic_write(out_dir / DATA_NAME, "wb") as f:
            for k in TREE_STREAMS:
                f.write(streams[k].tobytes())
        sv_max = 1.2 * max(m.lod.max_sv, tree_mod.tier_scales(ts)[-1] * ts[-1].lod.max_sv)
        cfg = {"model": MODEL_NAME, "data": DATA_NAME, "count": sum(counts), "streams": list(TREE_STREAMS),
               "settings": m.lod.to_dict(), "tree": {"counts": counts, "sv_max": sv_max}}
    else:  # one model: model.ply, its per-splat streams in clod.bin
        write_ply(out_dir / MODEL_NAME, m.with_sigma_d(None))
        streams = web_streams(m, static_scores)
        with atomic_write(out_dir / DATA_NAME, "wb") as f:
            for k in WEB_STREAMS:
                f.write(streams[k].tobytes())
        cfg = {"model": MODEL_NAME, "data": DATA_NAME, "count": len(m), "streams": list(WEB_STREAMS),
               "settings": {**(m.lod or LodSettings()).to_dict(), "fade_ramp_s_v": FADE_RAMP_S_V}}
    cfg.update({"engine": {"name": "playcanvas", "version": PLAYCANVAS_VERSION}, "cameras": cams})
    names = [MODEL_NAME, DATA_NAME]
    with atomic_write(out_dir / CONFIG_NAME, "w") as f:
        json.dump(cfg, f, indent=1)
    page = resources.files("clod_adapter.export") / "web_page"
    for name in PAGE_FILES:
        with atomic_write(out_dir / name, "wb") as f:
            f.write(page.joinpath(name).read_bytes())
    with atomic_write(out_dir / ENGINE_FILE, "wb") as f:
        with open(engine, "rb") as src:
            shutil.copyfileobj(src, f)
    return [*PAGE_FILES, ENGINE_FILE, *names, CONFIG_NAME]
