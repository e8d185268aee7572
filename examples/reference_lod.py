"""The merge-tree drawing rule of a ``clod-adapt`` model, from ``docs/lod_rule.md`` alone: numpy and
plyfile, no ``clod_adapter`` import. ``tests/test_tree.py`` holds the library to it, ``test_web_tree.py``
the web page's port (``export/web_page/clod_tree.mjs``). A model without merged tiers: ``reference_lod_plain.py``.

    python examples/reference_lod.py MODEL.ply [--s-v 2] [--budget K]   # what one camera draws

Float64 throughout. Cameras: ``viewmat`` [4, 4] world-to-camera (OpenCV axes), ``K`` [3, 3]
pixels, ``width``/``height`` pixels (gsplat 1.5.3 conventions).
"""
from __future__ import annotations

import argparse

import numpy as np
from plyfile import PlyData

F = 1.25  # the hand-over's width in s_v
M = 1.6  # a hand-over or an exit lasts over the last min(M, U / max(E, 1)) of a node's interval


def read_tree(path) -> list[dict]:
    """The tiers of a ``tree=True`` file, finest first, each a dict of arrays (``parent`` [N] int
    on all but the last, ``exit`` and ``d_ref`` [N] on all; docs/lod_rule.md "The file")."""
    ply = PlyData.read(str(path))
    assert any(c.split()[:1] == ["clod_lod"] and "tree=True" in c.split() for c in ply.comments), \
        "not a tree file: see reference_lod_plain.py"
    names, tiers, k = [e.name for e in ply.elements], [], 0
    while True:
        el = "vertex" if k == 0 else ("lod_parent" if k == 1 else f"lod_parent_{k}")
        if el not in names:
            return tiers
        v = ply[el].data
        col = lambda *ks: np.stack([np.asarray(v[x], np.float64) for x in ks], -1)  # noqa: E731
        rest = sorted((x for x in v.dtype.names if x.startswith("f_rest_")), key=lambda x: int(x[7:]))
        sh = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]
        if rest:  # f_rest is channel-major: [3, K-1] per Gaussian
            sh = np.concatenate([sh, col(*rest).reshape(len(v), 3, -1).transpose(0, 2, 1)], 1)
        tiers.append({"means": col("x", "y", "z"), "quats": col("rot_0", "rot_1", "rot_2", "rot_3"), "sh": sh,
                      "log_scales": col("scale_0", "scale_1", "scale_2"),
                      "opacity": 1 / (1 + np.exp(-col("opacity")[:, 0])),
                      "sigma_d": col("sigma_d")[:, 0],
                      **{p: np.asarray(v[p], np.int64 if p == "parent" else np.float64)
                         for p in ("parent", "exit", "d_ref") if p in v.dtype.names}})
        k += 1


def frustum(means, viewmat, K, width, height):
    """[N] bool: the centre in front (z > 0.01) and projecting inside the image."""
    p = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    x, y, z = p.T
    ax, ay = K[0, 0] * x + K[0, 2] * z, K[1, 1] * y + K[1, 2] * z
    return (z > 0.01) & (ax >= 0) & (ax < width * z) & (ay >= 0) & (ay < height * z)


def terms(tiers, viewmat, K, width, height, ref=False):
    """Steps 1-3 for one camera (with ``ref``, step 6's: ``d'`` the nodes' ``d_ref``): per tier the
    entry ``E``, the end ``U`` and whether a node fades."""
    c = -viewmat[:3, :3].T @ viewmat[:3, 3]
    d = [t["d_ref"] if ref else np.linalg.norm(t["means"] - c, axis=1) for t in tiers]
    frT = frustum(tiers[-1]["means"], viewmat, K, width, height)
    D = 1.0 if ref else max((d[-1][frT] if frT.any() else d[-1]).max(initial=0.0), 1e-12)
    d = [np.maximum(x / D, 1e-12) for x in d]
    T = len(tiers) - 1
    E = [np.zeros(len(d[0]))] + [None] * T
    for k in range(T, 0, -1):
        e = tiers[k]["sigma_d"] / d[k]
        if k < T:
            e = np.minimum(e, E[k + 1][tiers[k]["parent"]] / F)
        E[k] = np.maximum(e, F ** k)
    U, fade = [], []
    for k, t in enumerate(tiers):
        X = np.maximum(t["exit"] / d[k], F * np.maximum(E[k], 1.0))
        if k == T:
            U.append(X)
            fade.append(np.ones(len(X), bool))
        else:
            f = X < E[k + 1][t["parent"]]  # a lead's exit is +inf: it hands over
            U.append(np.where(f, X, E[k + 1][t["parent"]]))
            fade.append(f)
    return E, U, fade


def budget_s_v(tiers, E, U, viewmat, K, width, height, k):
    """Step 6: the smallest s_v >= 1 from which no cut (``terms(..., ref=True)``) holds over ``k`` centres in view."""
    frs = [frustum(t["means"], viewmat, K, width, height) for t in tiers]
    lo = np.maximum(np.concatenate([n[f] for n, f in zip(E, frs)]), 1.0)
    hi = np.concatenate([u[f] for u, f in zip(U, frs)])
    lo, hi = lo[hi > lo], hi[hi > lo]
    uniq, inv = np.unique(np.concatenate([lo, hi, [1.0]]), return_inverse=True)
    count = np.cumsum(np.bincount(inv, weights=np.concatenate([np.ones(len(lo)), -np.ones(len(hi)), [0.0]])))
    ok = np.flatnonzero(np.maximum.accumulate(count[::-1])[::-1] <= k)
    return float(uniq[ok[0]]) if ok.size else float(uniq[-1])


def draw(tiers, viewmat, K, width, height, s_v=None, budget=None) -> dict:
    """What one camera draws (steps 1-6), tier 0's rows first: ``ids`` (per tier), ``s_v``,
    ``means``, ``quats``, ``log_scales``, ``opacities``, ``sh`` [k, K, 3]."""
    viewmat, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    ns, ups, fades = terms(tiers, viewmat, K, width, height, ref=budget is not None)
    s = budget_s_v(tiers, ns, ups, viewmat, K, width, height, budget) if budget is not None else max(float(s_v), 1.0)
    out = {"ids": [], "s_v": s, "means": [], "quats": [], "log_scales": [], "opacities": [], "sh": []}
    for k, (t, n, u, f) in enumerate(zip(tiers, ns, ups, fades)):
        i = np.flatnonzero((n <= s) & (s < u))
        w, f = np.clip(np.log(u[i] / s) / np.log(np.minimum(M, u[i] / np.maximum(n[i], 1))), 0, 1), f[i]
        mu, q, ls, sh, a = t["means"][i], t["quats"][i], t["log_scales"][i], t["sh"][i], t["opacity"][i]
        if k + 1 < len(tiers):
            wh = np.where(f, 1.0, w)  # a row fading out keeps its attributes
            par, p = tiers[k + 1], t["parent"][i]
            q = q / np.linalg.norm(q, axis=1, keepdims=True)
            qp = par["quats"][p] / np.linalg.norm(par["quats"][p], axis=1, keepdims=True)
            qp = np.where((q * qp).sum(1, keepdims=True) < 0, -qp, qp)
            wc, lead = wh[:, None], np.isposinf(t["exit"][i])  # step 3's lead: its exit is +inf
            lc = lead[:, None]  # the lead grows into its parent; its siblings shrink and fade where they are
            mu = np.where(lc, wc * mu + (1 - wc) * par["means"][p], mu)
            ls = np.where(lc, wc * ls + (1 - wc) * par["log_scales"][p], ls + np.log(np.maximum(wc, 1e-4)))
            q = np.where(lc, wc * q + (1 - wc) * qp, q)
            sh = np.where(lc[:, :, None], wc[:, None] * sh + (1 - wc[:, None]) * par["sh"][p], sh)
            a = wh * a + (1 - wh) * np.where(lead, par["opacity"][p], 0.0)
        a = np.where(f, a * w, a)
        for key, val in (("ids", i), ("means", mu), ("quats", q), ("log_scales", ls), ("opacities", a), ("sh", sh)):
            out[key].append(val)
    return {k: (np.concatenate(v) if k not in ("ids", "s_v") else v) for k, v in out.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply")
    ap.add_argument("--s-v", type=float, default=2.0)
    ap.add_argument("--budget", type=int, default=None)
    a = ap.parse_args(argv)
    tiers = read_tree(a.ply)
    viewmat = np.eye(4)  # a camera 2.5 median radii behind the model's median, looking down +z
    centre = np.median(tiers[0]["means"], axis=0)
    viewmat[:3, 3] = np.array([0, 0, 2.5 * np.median(np.linalg.norm(tiers[0]["means"] - centre, axis=1))]) - centre
    d = draw(tiers, viewmat, np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), 640, 480, a.s_v, a.budget)
    print(f"{a.ply}: tiers of {[len(t['means']) for t in tiers]} Gaussians; at s_v = {d['s_v']:.3g} the cut draws "
          f"{[len(i) for i in d['ids']]} per tier")


if __name__ == "__main__":
    main()
