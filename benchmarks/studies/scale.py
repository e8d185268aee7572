"""How the cost of an adaptation step and of an evaluation frame grows with the model size N.

Usage: python -m benchmarks.studies.scale [--sizes 100000,300000,1000000] [--steps 6] [--threads 2]
       [--width 320 --height 240] [--views 16] [--tiers] [--out runs/scale.md]

Each size runs in a fresh subprocess (``--one N``), so sizes do not share caches or peak memory:

* the scene: :func:`clod_adapter.io.synthetic.make_ground_truth` with N Gaussians, SH degree 3
  (degree-2/3 coefficients added, small), scales shrunk by ``sqrt(6000 / N)`` so the surface
  coverage (Gaussians per pixel) stays that of the 6,000-Gaussian demo whatever N; a
  ``rows x cols`` grid of forward-facing cameras (:func:`make_cameras`) whose images are the
  ground truth rendered by our rasteriser; the "pretrained" model is a perturbed copy;
* ``prepare`` (the calibrated schedule's initialisation: LightGaussian ranking, reference
  distances, ``sigma_d``);
* ``--steps`` steps of :func:`clod_adapter.train.loop.fit` (the default calibrated schedule: a
  per-view exact budget of ``s_v^-1.5`` of the Gaussians in view, level gains, base attributes
  frozen), the first one discarded as warm-up; per step the wall time split into
  selection (frustum, in-view test, critical s_v, budget), projection, raster forward (SH,
  binning, compositor), backward, optimiser (Adam step + zero_grad) and the rest (loss, gains);
  medians over the steps;
* ``recalibrate`` (run once, after the last step);
* one evaluation frame (``render_lod`` at s_v = 1, no gradient; median of 3 after a warm-up);
* with ``--tiers``, the phases the merged tiers and the leave-out add to ``clod-adapt``: the faint
  Gaussians (:func:`clod_adapter.train.pruning.faint`, one render and backward per training view), the
  first merge (:func:`clod_adapter.train.tiers.decimated` to half the model: splat-transform's
  ``--decimate`` in a child process, whose own peak is ``ru_maxrss`` of the children) and its
  fit (:func:`clod_adapter.train.tiers.finetuned`, ``--steps`` steps; seconds per step). The tier's own
  adaptation is the same step on the smaller merged model. Then the merge tree of the adapted model
  and that merge (its ``sigma_d`` initialised by ``prepare``, handing over at ``s_v`` 1.75): its
  build (:func:`clod_adapter.lod.tree.build`: parents from a k-d tree, node constants on the
  training views), its fit on its cuts (:func:`clod_adapter.train.tree_fit.finetune`, ``--steps``
  steps; seconds per step) and a frame of it (:func:`clod_adapter.lod.draw.render_lod` at ``s_v`` 4
  and at a count budget of 30 % of the Gaussians in view; the median of 3 after a warm-up).

Peak memory is the process's resident high-water mark (``VmHWM`` of /proc/self/status), reset
before each phase (``echo 5 > /proc/self/clear_refs``), so each phase's peak is its own.
``base`` is the resident size before the model is built (Python, torch, the compositor).

The table is printed and written as Markdown (default ``runs/scale.md``, not in git) with the
fitted exponents ``b`` of ``time ~ N^b`` and ``peak - base ~ N^b`` (least squares in log-log
over the sizes run).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
PHASES = ("select", "project", "raster_fwd", "backward", "optimizer", "other")


def vm_kib(key: str) -> int:
    """``VmHWM`` / ``VmRSS`` of this process in KiB (0 when /proc is not there)."""
    try:
        m = re.search(rf"{key}:\s+(\d+)", Path("/proc/self/status").read_text())
        return int(m.group(1)) if m else 0
    except OSError:
        return 0


def reset_peak() -> bool:
    """Give freed heap memory back to the system (glibc ``malloc_trim``), then reset VmHWM to
    the current RSS (Linux >= 4.0), so the next peak is that of the next phase over what is
    live now; False when the reset is not possible."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def build(n: int, rows: int, cols: int, width: int, height: int, seed: int = 0):
    """(pretrained model, cameras, images) of the synthetic scene with ``n`` Gaussians."""
    import torch

    from clod_adapter.gaussians import Gaussians
    from clod_adapter.render import rasterization
    from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb

    torch.set_num_threads(2)
    gt = make_ground_truth(n, seed)
    g = torch.Generator().manual_seed(seed + 10)
    shN = torch.cat([gt.shN, 0.02 * torch.randn(n, 12, 3, generator=g)], 1)  # SH degree 3
    gt = Gaussians(means=gt.means, quats=gt.quats, log_scales=gt.log_scales + 0.5 * math.log(6000.0 / n),
                   opacity_logits=gt.opacity_logits, sh0=gt.sh0, shN=shN)
    cams = make_cameras(rows, cols, width, height)
    imgs = []
    with torch.no_grad():
        for c in cams:
            col, _, _ = rasterization(gt.means, gt.quats, gt.scales, gt.opacities, gt.colors, c.viewmat[None],
                                      c.K[None], c.width, c.height, sh_degree=3, backend="cpu")
            imgs.append(col[0].clamp(0, 1))
    pre = perturb(gt, seed + 1)
    del gt
    return pre, cams, imgs


class Timers:
    """Wall-time accumulators, filled by wrappers around the functions of one step."""

    def __init__(self) -> None:
        self.t = {k: 0.0 for k in PHASES}

    def reset(self) -> None:
        for k in self.t:
            self.t[k] = 0.0


def instrument(timers: Timers, state) -> None:
    """Wrap the functions a step calls so each adds its wall time to ``timers``."""
    import torch

    import clod_adapter.train.loop as ad

    real_render, real_bwd = ad.render_lod, torch.Tensor.backward

    def render_lod(*a, **k):  # LodRender splits a frame into projection / selection / raster itself
        out = real_render(*a, **k)
        timers.t["project"] += out.project_ms / 1e3
        timers.t["select"] += out.select_ms / 1e3
        timers.t["raster_fwd"] += out.raster_ms / 1e3
        return out

    def backward(self, *a, **k):
        t0 = time.perf_counter()
        out = real_bwd(self, *a, **k)
        timers.t["backward"] += time.perf_counter() - t0
        return out

    opt = state.optimizer
    real_step, real_zero = opt.step, opt.zero_grad

    def step(*a, **k):
        t0 = time.perf_counter()
        out = real_step(*a, **k)
        timers.t["optimizer"] += time.perf_counter() - t0
        return out

    def zero_grad(*a, **k):
        t0 = time.perf_counter()
        out = real_zero(*a, **k)
        timers.t["optimizer"] += time.perf_counter() - t0
        return out

    ad.render_lod, torch.Tensor.backward = render_lod, backward
    opt.step, opt.zero_grad = step, zero_grad


def write_scene(n: int, root: Path, args) -> None:
    """Build the scene with ``n`` Gaussians and write it as ``clod-adapt`` reads it: a COLMAP
    folder ``root/scene`` and the pretrained ``root/in.ply`` (skipped when already there)."""
    import numpy as np

    from clod_adapter.io.ply import write_ply
    from clod_adapter.io.colmap import write_colmap_scene

    if (root / "in.ply").is_file() and (root / "scene").is_dir():
        return
    model, cams, imgs = build(n, args.rows, args.cols, args.width, args.height)
    write_colmap_scene(root / "scene", cams, [(im.numpy() * 255 + 0.5).astype(np.uint8) for im in imgs])
    write_ply(root / "tmp.ply", model)
    (root / "tmp.ply").rename(root / "in.ply")


def one(n: int, args) -> dict:
    """Measure one size in this process; returns the row as a dict."""
    import torch

    torch.set_num_threads(args.threads)
    from clod_adapter.train.config import AdaptConfig
    from clod_adapter.train.loop import fit, prepare, recalibrate
    from clod_adapter.io.load import load_model
    from clod_adapter.io.load import load_scene
    from clod_adapter.io.view_images import ViewImages
    from clod_adapter.lod.draw import render_lod
    from clod_adapter.render.composite import cpp_extension_available

    assert cpp_extension_available(), "the C++ compositor is needed for timings"
    row = {"n": n, "threads": torch.get_num_threads(), "width": args.width, "height": args.height}
    can_reset = reset_peak()
    row["base_mb"] = vm_kib("VmRSS") / 1024
    root = Path(args.scenes) / f"n{n}"
    t0 = time.perf_counter()
    model = load_model(root / "in.ply")  # as clod-adapt reads it (memory-mapped .ply)
    scene = load_scene(root / "scene")
    scene.cache_size = 0
    row["load_s"] = time.perf_counter() - t0
    row["load_peak_mb"] = vm_kib("VmHWM") / 1024
    train = scene.train
    train_imgs = ViewImages(scene, train)
    test = (scene.test or scene.train)[0]

    cfg = AdaptConfig(max_sv=5.0, iterations=100000, seed=0)
    reset_peak()
    t0 = time.perf_counter()
    state = prepare(model, train, cfg)
    row["prepare_s"] = time.perf_counter() - t0
    row["prepare_peak_mb"] = vm_kib("VmHWM") / 1024
    reset_peak()
    row["before_steps_mb"] = vm_kib("VmRSS") / 1024  # input model + state (+ Adam) resident

    timers = Timers()
    instrument(timers, state)
    steps = []
    reset_peak()
    for i in range(args.steps):
        timers.reset()
        t0 = time.perf_counter()
        fit(state, train, train_imgs, cfg, progress=False, max_steps=1)
        total = time.perf_counter() - t0
        d = dict(timers.t)
        d["other"] = total - sum(v for k, v in d.items() if k != "other")
        d["total"] = total
        d["frac"] = state.history["eta"][-1]
        steps.append(d)
    row["step_peak_mb"] = vm_kib("VmHWM") / 1024
    timed = steps[1:] or steps
    med = lambda k: sorted(s[k] for s in timed)[len(timed) // 2]  # noqa: E731
    row["step"] = {k: med(k) for k in (*PHASES, "total")}
    row["step_frac_mean"] = sum(s["frac"] for s in timed) / len(timed)

    reset_peak()
    t0 = time.perf_counter()
    recalibrate(state, train, cfg)
    row["recalibrate_s"] = time.perf_counter() - t0
    row["recalibrate_peak_mb"] = vm_kib("VmHWM") / 1024

    g = state.gaussians().detach()
    reset_peak()
    frames = []
    with torch.no_grad():
        for i in range(4):
            timers.reset()
            t0 = time.perf_counter()
            out = render_lod(g, test, 1.0)
            total = time.perf_counter() - t0
            frames.append({"select": out.select_ms / 1e3, "project": out.project_ms / 1e3,
                           "raster_fwd": out.raster_ms / 1e3, "total": total, "drawn": out.n_rendered})
    row["eval_peak_mb"] = vm_kib("VmHWM") / 1024
    ft = frames[1:]
    row["eval"] = {k: sorted(f[k] for f in ft)[len(ft) // 2] for k in ("select", "project", "raster_fwd", "total")}
    row["eval_drawn"] = frames[-1]["drawn"]
    row["peak_reset"] = can_reset
    if args.tiers:
        del state
        tier_phases(row, model, g, train, train_imgs, test, cfg, args)
    return row


def tier_phases(row: dict, model, adapted, train, train_imgs, test, cfg, args) -> None:
    """The ``--tiers`` phases (module docstring) into ``row``: ``model`` the input, ``adapted`` it
    after the steps (the tree's tier 0)."""
    import resource

    import torch

    from clod_adapter.lod import tree
    from clod_adapter.lod.budget import Budget
    from clod_adapter.lod.draw import render_lod
    from clod_adapter.train import tiers, tree_fit
    from clod_adapter.train.loop import prepare
    from clod_adapter.train.pruning import faint

    reset_peak()
    t0 = time.perf_counter()
    out, _ = faint(model, train)
    row["faint_s"], row["faint_peak_mb"] = time.perf_counter() - t0, vm_kib("VmHWM") / 1024
    row["faint_left_out"] = int(out.sum())
    reset_peak()
    t0 = time.perf_counter()
    merged = tiers.decimated(model, 0.5)
    row["decimate_s"] = time.perf_counter() - t0
    row["decimate_child_peak_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    imgs = [train_imgs[i] for i in range(len(train))]
    reset_peak()
    t0 = time.perf_counter()
    merged = tiers.finetuned(merged, train, imgs, args.steps)
    row["tier_fit_s_per_step"] = (time.perf_counter() - t0) / args.steps
    row["tier_fit_peak_mb"] = vm_kib("VmHWM") / 1024
    # the merge tree of the model and its merge (sigma_d initialised as the job's tier adaptation starts)
    linked = tiers.attach(adapted, prepare(merged, train, cfg).gaussians().detach(), 1.75)
    reset_peak()
    t0 = time.perf_counter()
    model_tree = tree.build(linked, train)
    row["tree_build_s"], row["tree_build_peak_mb"] = time.perf_counter() - t0, vm_kib("VmHWM") / 1024
    reset_peak()
    t0 = time.perf_counter()
    tree_fit.finetune(model_tree, train, imgs, args.steps)
    row["tree_fit_s_per_step"] = (time.perf_counter() - t0) / args.steps
    row["tree_fit_peak_mb"] = vm_kib("VmHWM") / 1024
    for key, kw in (("tree_frame_s", {"s_v": 4.0}), ("tree_budget_frame_s", {"budget": Budget(in_view=0.3)})):
        ts = []
        with torch.no_grad():
            for _ in range(4):
                t0 = time.perf_counter()
                render_lod(model_tree, test, **kw)
                ts.append(time.perf_counter() - t0)
        row[key] = sorted(ts[1:])[1]  # the median after a warm-up frame


def fit_exponent(xs, ys) -> float:
    """Least-squares slope of log y against log x."""
    lx = [math.log(x) for x in xs]
    ly = [math.log(max(y, 1e-12)) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    den = sum((a - mx) ** 2 for a in lx)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / den if den > 0 else float("nan")


def markdown(rows: list, args, load: str) -> str:
    ns = [r["n"] for r in rows]
    hdr = ("| N | s/step | select | project | raster fwd | backward | optimiser | other | peak MB (step) "
           "| bytes/G | resident before steps MB | eval frame s | eval peak MB | load peak MB | prepare s "
           "| prepare peak MB | recalibrate s |")
    out = [hdr, "|" + "---:|" * 17]
    for r in rows:
        s, e = r["step"], r["eval"]
        out.append(f"| {r['n']:,} | {s['total']:.3f} | {s['select']:.3f} | {s['project']:.3f} | {s['raster_fwd']:.3f} "
                   f"| {s['backward']:.3f} | {s['optimizer']:.3f} | {s['other']:.3f} | {r['step_peak_mb']:.0f} "
                   f"| {(r['step_peak_mb'] - r['base_mb']) * 2**20 / r['n']:.0f} | {r['before_steps_mb']:.0f} "
                   f"| {e['total']:.3f} | {r['eval_peak_mb']:.0f} | {r['load_peak_mb']:.0f} | {r['prepare_s']:.1f} "
                   f"| {r['prepare_peak_mb']:.0f} | {r['recalibrate_s']:.2f} |")
    lines = ["\n".join(out), ""]
    if all("decimate_s" in r for r in rows):
        lines += [tier_markdown(rows), ""]
    if len(rows) >= 2:
        ex = {
            "s/step": fit_exponent(ns, [r["step"]["total"] for r in rows]),
            "step peak - base": fit_exponent(ns, [r["step_peak_mb"] - r["base_mb"] for r in rows]),
            "eval frame s": fit_exponent(ns, [r["eval"]["total"] for r in rows]),
            "eval peak - base": fit_exponent(ns, [r["eval_peak_mb"] - r["base_mb"] for r in rows]),
            "prepare s": fit_exponent(ns, [r["prepare_s"] for r in rows]),
        }
        for k in ("select", "project", "raster_fwd", "backward", "optimizer"):
            ex[k] = fit_exponent(ns, [r["step"][k] for r in rows])
        lines.append("Fitted exponents b (cost ~ N^b, least squares over the sizes): "
                     + ", ".join(f"{k} {v:.2f}" for k, v in ex.items()) + ".")
        loc = []
        for a, b in zip(rows[:-1], rows[1:]):
            loc.append(f"{a['n']:,} -> {b['n']:,}: s/step "
                       f"{fit_exponent([a['n'], b['n']], [a['step']['total'], b['step']['total']]):.2f}, step peak - base "
                       f"{fit_exponent([a['n'], b['n']], [a['step_peak_mb'] - a['base_mb'], b['step_peak_mb'] - b['base_mb']]):.2f}, "
                       f"eval s {fit_exponent([a['n'], b['n']], [a['eval']['total'], b['eval']['total']]):.2f}")
        lines.append("Between consecutive sizes (fixed per-pixel and per-process costs weigh less at large N, "
                     "so these tend to 1 for linear growth): " + "; ".join(loc) + ".")
    r0 = rows[0]
    fracs = ", ".join(f"{r['step_frac_mean']:.2f}" for r in rows)
    lines.append(f"\n{r0['threads']} threads, {args.width}x{args.height}, {args.rows * args.cols} views "
                 f"({sum(1 for i in range(args.rows * args.cols) if i % 8)} trained), SH degree 3, "
                 f"{args.steps} steps per size (first discarded, medians), base RSS {r0['base_mb']:.0f} MB "
                 f"(Python, torch, compositor; bytes/G = (step peak - base) / N); mean drawn share per step "
                 f"{fracs}; load: {load}.")
    return "\n".join(lines)


def tier_markdown(rows: list) -> str:
    """The ``--tiers`` phases' table, with each column's fitted exponent."""
    ns = [r["n"] for r in rows]
    cols = [("faint s", "faint_s"), ("faint peak MB", "faint_peak_mb"), ("merge s", "decimate_s"),
            ("merge child peak MB", "decimate_child_peak_mb"), ("tier fit s/step", "tier_fit_s_per_step"),
            ("tier fit peak MB", "tier_fit_peak_mb"), ("tree build s", "tree_build_s"),
            ("tree build peak MB", "tree_build_peak_mb"), ("tree fit s/step", "tree_fit_s_per_step"),
            ("tree fit peak MB", "tree_fit_peak_mb"), ("tree frame s (s_v 4)", "tree_frame_s"),
            ("tree frame s (30 % in view)", "tree_budget_frame_s")]
    out = ["| N | left out | " + " | ".join(c for c, _ in cols) + " |", "|" + "---:|" * (len(cols) + 2)]
    for r in rows:
        out.append(f"| {r['n']:,} | {r['faint_left_out']:,} | " + " | ".join(
            f"{r[k]:.0f}" if k.endswith("_mb") else f"{r[k]:.3f}" for _, k in cols) + " |")
    if len(rows) >= 2:
        base = [r["base_mb"] for r in rows]
        ex = [f"{c} {fit_exponent(ns, [r[k] - (b if k.endswith('_mb') and 'child' not in k else 0) for r, b in zip(rows, base)]):.2f}"
              for c, k in cols]
        out.append("\nFitted exponents b (cost ~ N^b; peaks less the base RSS, the merge's child peak as it is): "
                   + ", ".join(ex) + ".")
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="100000,300000,1000000")
    p.add_argument("--steps", type=int, default=6)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--rows", type=int, default=4)
    p.add_argument("--cols", type=int, default=4)
    p.add_argument("--tiers", action="store_true",
                   help="also time the phases the merged tiers and the leave-out add (module docstring)")
    p.add_argument("--out", default=str(REPO / "runs" / "scale.md"))
    p.add_argument("--scenes", default=str(REPO / "runs" / "scale_scenes"),
                   help="where the synthetic scenes are written (reused when there)")
    p.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--json", default=None, help=argparse.SUPPRESS)
    p.add_argument("--build", type=int, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.build is not None:
        root = Path(args.scenes) / f"n{args.build}"
        root.mkdir(parents=True, exist_ok=True)
        write_scene(args.build, root, args)
        return 0
    if args.one is not None:
        row = one(args.one, args)
        Path(args.json).write_text(json.dumps(row))
        return 0
    sizes = [int(float(s)) for s in args.sizes.split(",")]
    rows = []
    load0 = os.getloadavg()
    for n in sizes:
        js = Path(args.out).with_suffix(f".{n}.json")
        js.parent.mkdir(parents=True, exist_ok=True)
        common = [f"--{k}={getattr(args, k)}" for k in ("steps", "threads", "width", "height", "rows", "cols",
                                                         "scenes")] + (["--tiers"] if args.tiers else [])
        env = dict(os.environ, OMP_NUM_THREADS=str(args.threads))
        print(f"scale: N = {n:,}: building the scene (cached in {args.scenes}) ...", file=sys.stderr, flush=True)
        r = subprocess.run([sys.executable, "-m", "benchmarks.studies.scale", "--build", str(n)] + common, env=env, cwd=REPO)
        if r.returncode != 0:
            print(f"scale: building N = {n:,} failed (exit {r.returncode}); stopping", file=sys.stderr)
            break
        print(f"scale: N = {n:,}: measuring ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "benchmarks.studies.scale", "--one", str(n), "--json", str(js)] + common, env=env,
                           cwd=REPO)
        if r.returncode != 0:
            print(f"scale: N = {n:,} failed (exit {r.returncode}); stopping", file=sys.stderr)
            break
        rows.append(json.loads(js.read_text()))
        print(f"scale: N = {n:,}: {rows[-1]['step']['total']:.2f} s/step, peak {rows[-1]['step_peak_mb']:.0f} MB "
              f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    if not rows:
        return 1
    load1 = os.getloadavg()
    load = f"1-min load average {load0[0]:.1f} at the start, {load1[0]:.1f} at the end"
    md = markdown(rows, args, load)
    print(md)
    Path(args.out).write_text(md + "\n")
    print(f"scale: wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
