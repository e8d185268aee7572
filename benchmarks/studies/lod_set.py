"""The streamed LoD set (``clod-export --lod-meta``) against splat-transform's own LoD levels.

For each input (default: fern and skull, a 360-degree capture) this takes the default adaptation
(cached, common.py) and builds two PlayCanvas streamed-SOG LoD sets with splat-transform 3.7.0:

* ``clod``: the adapted model's levels as ``clod-export --lod-meta`` cuts them
  (:func:`clod_adapter.export.bake.lod_set_levels`: a merge tree cut at each node's reference
  distance, as many nodes per level as each merged tier; a model without one cut at each of
  :func:`clod_adapter.export.bake.lod_set_s_vs`, reference distances from the fit views);
* ``decimate`` / ``decimate_adaptive``: splat-transform's own levels for the same counts, the
  chain a LoD builder runs: level 0 the input, level k + 1 the tool's ``--decimate`` (or
  ``--decimate-adaptive``) of level k down to our level k + 1's count;
* ``ordered``: the prefixes of ``clod-export --ordered``'s file (:func:`clod_adapter.export.bake.importance_order`
  over the fit views, base attributes: what a viewer that streams the file in order draws) at
  the same counts, scored as plain .ply files.

Every level is read back out of its ``lod-meta.json`` (``splat-transform SET -L k out.ply``: the
SOG-compressed data a viewer streams; ``--no-sog``: the plain .ply levels, ``set_bytes`` 0) and
drawn whole by our CPU rasteriser from the evaluation views (``--split test``: the test views, the
table in docs/studies.md; ``val``: validation views). Goal (the exported levels and the ordered
file's prefixes >= the decimators at equal count): at every level below full detail, PSNR >= the
better decimator's, for the LoD set and for the prefixes; the script prints the margins and exits
1 when one is missed. Outputs ``runs/bench/lod_set{_val}/<input>.csv`` (one per input run) and
``summary.md`` (every input with a .csv there; ``--summary-only`` rewrites it without running)::

    python -m benchmarks.studies.lod_set                 # fern and skull, test views
    python -m benchmarks.studies.lod_set --inputs skull --split val
    python -m benchmarks.studies.lod_set --no-sog --split val --tree-levels tiers   # the tiers whole

``--tree-levels tiers`` exports a merge tree's tiers whole instead of the tree's own cut at each
node's reference distance (:func:`clod_adapter.export.bake.lod_set_levels`); written under
``runs/bench/lod_set_tiers{_val}``.
"""
from __future__ import annotations

import csv
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import LABELS, RUNS, adapt_cached, load_input, parse_inputs_args, scene_views, split_suffix, table  # noqa: E402

import torch

from clod_adapter.export.bake import importance_order, lod_set_levels
from clod_adapter.lod.rankings import merge_decimate
from clod_adapter.lod.draw import render_lod
from clod_adapter.io.load import load_model
from clod_adapter.io.ply import write_ply
from clod_adapter.metrics import psnr, ssim
from clod_adapter.io.splat_transform import find_splat_transform, run_splat_transform, write_lod_set
from clod_adapter.train.config import AdaptConfig

PEERS = {"decimate": "decimate", "decimate_adaptive": "adaptive"}
COLUMNS = ["input", "method", "level", "s_v", "gaussians", "psnr", "ssim", "set_bytes"]


def read_levels(lod_meta: Path, n_levels: int, tmp: Path) -> list:
    """Every level of a LoD set as splat-transform reads it back (``-L k``), finest first."""
    out = []
    for k in range(n_levels):
        dst = tmp / f"read_{lod_meta.parent.name}_{k}.ply"
        run_splat_transform([str(lod_meta), "-L", str(k), "-w", str(dst)], what=f"-L {k}")
        out.append(load_model(dst))
    return out


def score(g, cams, gts) -> tuple[float, float]:
    ims = [render_lod(g, c).image.clamp(0, 1) for c in cams]
    return (sum(psnr(i, t) for i, t in zip(ims, gts)) / len(ims),
            sum(float(ssim(i, t)) for i, t in zip(ims, gts)) / len(ims))


def build_set(name: str, levels: list, root: Path, tmp: Path, sh_iterations=None) -> tuple[Path, int]:
    """Write ``levels`` as a LoD set under ``root/name``; (its lod-meta.json, its bytes)."""
    plys = [write_ply(tmp / f"{name}_{k}.ply", g) for k, g in enumerate(levels)]
    out = root / name
    if out.exists():
        import shutil

        shutil.rmtree(out)
    write_lod_set(plys, out, sh_iterations=sh_iterations)
    return out / "lod-meta.json", sum(p.stat().st_size for p in out.rglob("*") if p.is_file())


def run_input(name: str, split: str, log, sh_iterations=None, sog: bool = True, tree_levels: str = "cut") -> list[dict]:
    ply = adapt_cached(name, AdaptConfig(), "default", split=split, log=log)
    g0, scene, gts = load_input(name, split)
    fit, cams = scene_views(scene, split)
    ga = load_model(ply)
    t0 = time.perf_counter()
    with torch.no_grad():
        ours, s_vs = zip(*lod_set_levels(ga, fit, tree_levels=tree_levels))
    ours, s_vs = list(ours), ["" if s is None else s for s in s_vs]
    counts = [len(g) for g in ours]
    log(f"[{name}] baked {len(s_vs)} levels {counts} in {time.perf_counter() - t0:.0f} s")
    sets = {"clod": ours}
    for method, mode in PEERS.items():
        chain = [g0]
        for c in counts[1:]:
            chain.append(merge_decimate(chain[-1], c, mode=mode))
        sets[method] = chain
    with torch.no_grad():
        perm = importance_order(ga, fit)
    plain = ga.with_sigma_d(None)
    ordered = [plain.subset(perm[:c]) for c in counts]  # the file's prefixes (base attributes)
    rows = []
    root = RUNS / f"lod_set{split_suffix(split)}" / name
    with tempfile.TemporaryDirectory(prefix="clod-lodset-") as d, torch.no_grad():
        for method, levels in sets.items():
            nbytes = 0
            if sog:
                meta, nbytes = build_set(method, levels, root, Path(d), sh_iterations)
                levels = read_levels(meta, len(levels), Path(d))
            for k, g in enumerate(levels):
                p, s = score(g, cams, gts)
                rows.append({"input": name, "method": method, "level": k, "s_v": s_vs[k] if method == "clod" else "",
                             "gaussians": len(g), "psnr": round(p, 3), "ssim": round(s, 4), "set_bytes": nbytes})
                log(f"[{name}] {method} level {k}: {len(g):,} Gaussians, {p:.2f} dB")
        for k, g in enumerate(ordered):
            p, s = score(g, cams, gts)
            rows.append({"input": name, "method": "ordered", "level": k, "s_v": "", "gaussians": len(g),
                         "psnr": round(p, 3), "ssim": round(s, 4), "set_bytes": 0})
            log(f"[{name}] ordered prefix {k}: {len(g):,} Gaussians, {p:.2f} dB")
    return rows


def margins(rows: list[dict], ours: str = "clod") -> list[dict]:
    """Per input and level >= 1: ``ours`` (the LoD set ``clod`` or the ``ordered`` prefixes) - the
    better decimator's PSNR (the goal: >= 0)."""
    out = []
    for name in dict.fromkeys(r["input"] for r in rows):
        mine = {r["level"]: r for r in rows if r["input"] == name and r["method"] == ours}
        for k, r in sorted(mine.items()):
            if k == 0:
                continue
            peers = [q for q in rows if q["input"] == name and q["method"] in PEERS and q["level"] == k]
            best = max(peers, key=lambda q: q["psnr"])
            out.append({"input": name, "what": ours, "level": k, "count": r["gaussians"], "ours": r["psnr"],
                        "best": best["psnr"], "peer": best["method"], "margin": round(r["psnr"] - best["psnr"], 3)})
    return out


def main(argv=None) -> int:
    a = parse_inputs_args(__doc__, argv, extra=[
        ("--sog-sh-iterations", {"type": int, "default": None, "help": "splat-transform --sh-iterations"}),
        ("--summary-only", {"action": "store_true", "help": "rewrite summary.md from the .csv files there"}),
        ("--no-sog", {"action": "store_true", "help": "score the levels as plain .ply files, without building and "
                                                      "reading back the SOG sets (their SH k-means is slow on the CPU)"}),
        ("--tree-levels", {"choices": ["cut", "tiers"], "default": "cut",
                           "help": "a merge tree's levels (export.bake.lod_set_levels; default cut)"})])
    if find_splat_transform() is None:
        sys.exit("benchmark: splat-transform not found (`npm ci` in the repository root installs 3.7.0)")
    log = lambda *x: print(*x, flush=True)  # noqa: E731
    out = RUNS / f"lod_set{'' if a.tree_levels == 'cut' else '_' + a.tree_levels}{split_suffix(a.split)}"
    out.mkdir(parents=True, exist_ok=True)
    for name in [] if a.summary_only else a.inputs:
        with open(out / f"{name}.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(run_input(name, a.split, log, a.sog_sh_iterations, sog=not a.no_sog, tree_levels=a.tree_levels))
    names = [n for n in LABELS if (out / f"{n}.csv").is_file()]
    rows = [r for n in names for r in csv.DictReader(open(out / f"{n}.csv"))]
    for r in rows:
        r.update(level=int(r["level"]), gaussians=int(r["gaussians"]), psnr=float(r["psnr"]), ssim=float(r["ssim"]),
                 set_bytes=int(r["set_bytes"]))
    lines = []
    for name in names:
        rs = [r for r in rows if r["input"] == name]
        levels = sorted({r["level"] for r in rs})
        body = []
        for method in ["clod", *PEERS, "ordered"]:
            cells = {r["level"]: r for r in rs if r["method"] == method}
            if not cells:
                continue
            body.append([method] + [f"{cells[k]['psnr']:.2f} / {cells[k]['ssim']:.3f} ({cells[k]['gaussians']:,})"
                                    for k in levels] + [f"{cells[0]['set_bytes'] / 1e6:.2f}" if cells[0]["set_bytes"] else "- (plain .ply)"])
        lines += [f"#### {LABELS[name]}", "",
                  table(["LoD set"] + [f"level {k}" for k in levels] + ["MB"], body), ""]
    ms = margins(rows) + margins(rows, "ordered")
    lines += ["| input | ours | level | Gaussians | ours dB | best decimator dB | margin | met |",
              "|---|---|---:|---:|---:|---:|---:|---|"]
    lines += [f"| {m['input']} | {m['what']} | {m['level']} | {m['count']:,} | {m['ours']:.2f} | {m['best']:.2f} ({m['peer']}) | "
              f"{m['margin']:+.2f} | {'yes' if m['margin'] >= 0 else '**no**'} |" for m in ms]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    missed = [m for m in ms if m["margin"] < 0]
    print(f"{len(ms) - len(missed)} of {len(ms)} levels (LoD set and ordered prefixes) at or above the better decimator")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
