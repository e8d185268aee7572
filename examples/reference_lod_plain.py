"""The drawing rule of a ``clod-adapt`` model without merged tiers, from ``docs/lod_rule_plain.md``
alone: numpy and plyfile, no ``clod_adapter`` import. For renderers that want the rule without the
library (copy this file), and as the library's check that the page says all it does
(``tests/test_reference_lod.py``). A model with merged tiers is a merge tree: ``reference_lod.py``.

    python examples/reference_lod_plain.py MODEL.ply [--s-v 2]        # prints what one camera draws

Everything is float64. Cameras: ``viewmat`` [4, 4] world-to-camera (OpenCV axes, z forward),
``K`` [3, 3] pixels, ``width``/``height`` pixels (gsplat 1.5.3 conventions).
"""
from __future__ import annotations

import argparse
import math

import numpy as np
from plyfile import PlyData

NEAR, FAR, EPS2D, EXTEND = 0.01, 1e10, 0.3, 3.33
RAMP_MIN = 1.1  # the window opens and the ramp ends no earlier than here
DEFAULTS = {"max_sv": 5.0, "tau": 0.005, "eps": 1e-8, "fade": "eq2", "fade_width": 0.75, "level_max": 1.0}
#: the ``clod_lod`` keys that are not numbers
WORDS = ("fade", "count_mix", "tree")


def read_model(path) -> dict:
    """The arrays and settings of an extended .ply (docs/lod_rule_plain.md, "The file"): ``means``
    [N, 3], ``quats`` [N, 4] wxyz, ``log_scales`` [N, 3], ``opacity_logits`` [N], ``sh0`` [N, 3],
    ``sigma_d`` [N], gains ``g_o`` [N], ``g_s`` [N], ``g_c`` [N, 3] (0 when absent), ``settings``.
    A file with merged tiers (a ``lod_parent`` element) is a merge tree: ``reference_lod.py``."""
    ply = PlyData.read(str(path))
    assert "lod_parent" not in [e.name for e in ply.elements], "a file with merged tiers: see reference_lod.py"
    settings = dict(DEFAULTS)
    for c in ply.comments:
        parts = c.split()
        if parts and parts[0] == "clod_lod":
            for kv in parts[1:]:
                k, _, val = kv.partition("=")
                settings[k] = val if k in WORDS else float(val)  # count_mix: written by earlier versions, not drawn
    return _element(ply["vertex"].data, settings)


def _element(v, settings) -> dict:
    names = v.dtype.names

    def cols(*keys):
        return np.stack([np.asarray(v[k], dtype=np.float64) for k in keys], axis=-1)

    def gain(*keys):
        return cols(*keys) if all(k in names for k in keys) else np.zeros((len(v), len(keys)))

    return {"means": cols("x", "y", "z"), "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
            "log_scales": cols("scale_0", "scale_1", "scale_2"), "opacity_logits": cols("opacity")[:, 0],
            "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2"), "sigma_d": cols("sigma_d")[:, 0],
            "g_o": gain("opacity_gain")[:, 0], "g_s": gain("scale_gain")[:, 0],
            "g_c": gain("f_dc_gain_0", "f_dc_gain_1", "f_dc_gain_2"), "settings": settings}


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def frustum(means, viewmat, K, width, height):
    """Step 1: [N] bool, the centre in front of the camera and projecting inside the image."""
    p = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = K[0, 0] * x + K[0, 2] * z
    ay = K[1, 1] * y + K[1, 2] * z
    return (z > NEAR) & (ax >= 0) & (ax < width * z) & (ay >= 0) & (ay < height * z)


def normalized_distances(means, viewmat, fr):
    """Step 2: [N] d'."""
    c = -viewmat[:3, :3].T @ viewmat[:3, 3]
    d = np.linalg.norm(means - c, axis=1)
    if d.size == 0:
        return d
    dmax = d[fr].max() if fr.any() else d.max()
    return d / max(dmax, 1e-12)


def quat_to_rotmat(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def in_view(means, quats, log_scales, viewmat, K, width, height):
    """Step 3: [N] bool, gsplat 1.5.3's projection culling at these scales, opacity-free."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.T
    ok = (z >= NEAR) & (z <= FAR)
    z = np.where(ok, z, 1.0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tx, ty = 0.5 * width / fx, 0.5 * height / fy
    u = np.clip(x / z, -(cx / fx + 0.3 * tx), (width - cx) / fx + 0.3 * tx)
    v = np.clip(y / z, -(cy / fy + 0.3 * ty), (height - cy) / fy + 0.3 * ty)
    J = np.zeros((len(z), 2, 3))
    J[:, 0, 0], J[:, 0, 2] = fx / z, -fx * u / z
    J[:, 1, 1], J[:, 1, 2] = fy / z, -fy * v / z
    M = J @ R @ quat_to_rotmat(quats) * np.exp(log_scales)[:, None, :]
    cov = M @ M.transpose(0, 2, 1) + EPS2D * np.eye(2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    rx = np.ceil(EXTEND * np.sqrt(cov[:, 0, 0]))
    ry = np.ceil(EXTEND * np.sqrt(cov[:, 1, 1]))
    mx, my = fx * x / z + cx, fy * y / z + cy
    return ok & (det > 0) & ~((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height))


def margins(m, d_norm, s):
    """Step 4: [N] m_i(s) = log alpha'' - log(tau s)."""
    st = m["settings"]
    with np.errstate(divide="ignore"):
        log_alpha = np.log(sigmoid(m["opacity_logits"]))
    den = 2.0 * np.maximum(m["sigma_d"], 0.0) ** 2 + max(st["eps"], 1e-20)
    return log_alpha - (d_norm * s) ** 2 / den - math.log(st["tau"] * s)


def level_of_share(p, st):
    """``L(p)``: the level of the gains when a share ``p`` of the frustum's Gaussians is drawn."""
    if not st["max_sv"] > 1.0:
        return 0.0
    if not p > 0.0:
        return st["level_max"]
    s = min(p, 1.0) ** (-2.0 / 3.0)
    return min(max(math.log(s) / math.log(st["max_sv"]), 0.0), st["level_max"])


def draw(m, viewmat, K, width, height, s_v: float) -> dict:
    """What one camera draws at ``s_v >= 1`` (docs/lod_rule_plain.md): ``ids`` [k] ascending,
    ``opacities`` [k] (activated), ``log_scales`` [k, 3], ``sh0`` [k, 3] at the level, ``level``."""
    st = m["settings"]
    viewmat, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    fr = frustum(m["means"], viewmat, K, width, height)
    d = normalized_distances(m["means"], viewmat, fr)
    vis = in_view(m["means"], m["quats"], m["log_scales"], viewmat, K, width, height)
    n_f = int(fr.sum())
    mar = margins(m, d, s_v)
    keep = (mar > 0) & vis
    p = keep.sum() / n_f if n_f else 1.0
    if st["fade"] == "eq2":
        ids, level = np.flatnonzero(keep), 0.0
        att = np.exp(-(d[ids] * s_v) ** 2 / (2.0 * np.maximum(m["sigma_d"][ids], 0.0) ** 2 + max(st["eps"], 1e-20)))
        op = sigmoid(m["opacity_logits"][ids]) * att
    else:
        w = st["fade_width"] * min(1.0, math.log(s_v) / math.log(RAMP_MIN))
        fade = np.clip(mar / w, 0.0, 1.0) if w > 0 else (mar > 0).astype(np.float64)
        q = ((margins(m, d, 1.0) > 0) & fr).sum() / n_f if n_f else 1.0
        ramp_end = min(max(RAMP_MIN * q ** (-2.0 / 3.0), RAMP_MIN), max(RAMP_MIN, math.sqrt(st["max_sv"]))) \
            if q > 0 else max(RAMP_MIN, math.sqrt(st["max_sv"]))
        if s_v <= 1.0:
            ids, level, weight = np.flatnonzero(vis), 0.0, 1.0
        elif s_v < ramp_end:
            t = math.log(s_v) / math.log(ramp_end)
            ids, level = np.flatnonzero(vis), t * level_of_share(p, st)
            weight = (1.0 - t) + t * fade[ids]
        else:
            ids, level = np.flatnonzero(keep), level_of_share(p, st)
            weight = fade[ids]
        op = sigmoid(m["opacity_logits"][ids] + level * m["g_o"][ids]) * weight
    return {"ids": ids, "opacities": op, "level": level,
            "log_scales": m["log_scales"][ids] + level * m["g_s"][ids, None],
            "sh0": m["sh0"][ids] + level * m["g_c"][ids]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply")
    ap.add_argument("--s-v", type=float, default=2.0)
    a = ap.parse_args(argv)
    m = read_model(a.ply)
    # a camera 2.5 median radii behind the model's median, looking down +z, 640x480
    centre = np.median(m["means"], axis=0)
    radius = float(np.median(np.linalg.norm(m["means"] - centre, axis=1)))
    viewmat = np.eye(4)
    viewmat[:3, 3] = -(centre - np.array([0.0, 0.0, 2.5 * radius]))
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    out = draw(m, viewmat, K, 640, 480, a.s_v)
    print(f"{a.ply}: {len(m['means'])} Gaussians, {m['settings']}")
    print(f"  s_v = {a.s_v:g}: draws {out['ids'].size} at level {out['level']:.3f}, "
          f"mean opacity {out['opacities'].mean() if out['ids'].size else 0:.3f}")


if __name__ == "__main__":
    main()
