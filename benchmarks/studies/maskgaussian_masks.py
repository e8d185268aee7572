"""Which Gaussians to keep from a MaskGaussian .ply that holds its mask scores (masks_0/masks_1)?

MaskGaussian (Liu et al., CVPR 2025; kaikai23/MaskGaussian) learns two scores per Gaussian and
renders with the hard straight-through Gumbel-softmax mask ``gumbel_softmax(log_softmax([masks_0,
masks_1]), hard=True)[:, 0]``. Its official save draws that mask once and writes the kept
Gaussians; its unused ``save_ply`` writes all of them with the scores. This benchmark makes such a
file and scores the loading policies of ``clod_adapter.io.load.apply_masks`` on it:

1. a short MaskGaussian-style post-training of the vanilla fern checkpoint (all attributes plus
   the mask scores, init (10, 1); loss ``0.8 L1 + 0.2 (1 - SSIM + lambda_mask mean(mask)^2)``,
   lambda_mask 0.1, as ``prune_finetune.py`` and ``shared/data/fern/maskgaussian/TRAINING.md``),
   on our CPU rasteriser with the mask multiplied into the opacity, saved with ``masks_0``,
   ``masks_1`` to ``runs/bench/maskgaussian_masks/point_cloud.ply`` (reused when its settings
   match; ``--retrain`` redoes it);
2. PSNR / SSIM on the validation views (``--split val``, the default: post-trained on the fit
   views; ``--split test``: on the training views, scored on the test views) and the kept count for ``argmax`` (p(keep) > 0.5), ``gumbel`` (one draw,
   ``--seeds`` seeds: mean, spread) and ``all``, next to the vanilla input; prints a table and
   writes it to ``runs/bench/maskgaussian_masks/table.md``.

    python -m benchmarks.studies.maskgaussian_masks [--steps 300] [--mask-lr 0.03] [--seeds 8] [--split val]

Deviations from the official recipe (to finish in about 5 minutes on 2 CPU cores): ``--steps``
(300) instead of 1,500-5,000 post-training iterations, with the mask learning rate scaled up
(0.03 instead of 0.01) so the scores can travel about as far; no 0.95-per-400-steps decay
(shorter than one period); fresh Adam moments. A Gaussian the drawn mask switches off gets no
rendering gradient in that step (our rasteriser skips alpha < 1/255; MaskGaussian's kernels
still give it dL/dmask), so masks lean a little further towards pruning than the official code's.
With the defaults the p(keep) histogram is close to that of the 1,500-iteration run in
``shared/data/fern/maskgaussian`` (TRAINING.md): 18,852 / 3,421 / 2,807 / 14,897 Gaussians in
[0, 0.05) / [0.05, 0.5) / [0.5, 0.95) / [0.95, 1] against 17,961 / 2,558 / 3,407 / 16,051.

The table and the choice it made: docs/studies.md, "Inputs: MaskGaussian masks".
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

from benchmarks.common import add_split_arg, scene_views  # noqa: E402

from clod_adapter.train.official import ADAM_EPS, means_lr, official_groups, scene_extent  # noqa: E402
from clod_adapter.evaluate.level_metrics import evaluate_level  # noqa: E402
from clod_adapter.gaussians import Gaussians  # noqa: E402
from clod_adapter.io.load import apply_masks, load_model  # noqa: E402
from clod_adapter.io.ply import read_ply, write_ply  # noqa: E402
from clod_adapter.io.load import load_scene  # noqa: E402
from clod_adapter.metrics import psnr, ssim  # noqa: E402
from clod_adapter.render import rasterization  # noqa: E402

SHARED = Path(os.environ.get("CLOD_SHARED_DATA") or REPO.parent / "shared" / "data")
FERN = SHARED / "fern"
OUT = REPO / "runs" / "bench" / "maskgaussian_masks"
ATTRS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")
MASK_INIT = (10.0, 1.0)  # gaussian_model.py: mask scores start at (10, 1), p(keep) = sigmoid(9)
LAMBDA_DSSIM = 0.2


def st_gumbel_mask(scores: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """[N] hard keep mask, straight-through: ``gumbel_softmax(log_softmax(scores), tau=1,
    hard=True)[:, 0]`` with Gumbel noise from ``gen`` (forward 0/1, gradient of the soft sample)."""
    u = torch.rand(scores.shape, generator=gen).clamp_(1e-10, 1.0 - 1e-7)
    y = F.softmax(F.log_softmax(scores, dim=-1) - torch.log(-torch.log(u)), dim=-1)
    hard = F.one_hot(y.argmax(-1), 2).to(y)
    return (hard - y.detach() + y)[:, 0]


def render(g: dict, opacities: torch.Tensor, cam, sh_degree: int) -> torch.Tensor:
    colors = torch.cat([g["sh0"], g["shN"]], dim=1)
    img, _, _ = rasterization(g["means"], g["quats"], torch.exp(g["log_scales"]), opacities, colors,
                              cam.viewmat[None], cam.K[None], cam.width, cam.height,
                              sh_degree=sh_degree, backend="cpu")
    return img[0]


def train(ply: Path, cams: list, images, args, out_ply: Path) -> dict:
    """MaskGaussian-style post-training of ``ply``; writes ``out_ply`` with masks_0/masks_1."""
    g0 = read_ply(ply)
    n = len(g0)
    params = {k: torch.nn.Parameter(getattr(g0, k).clone()) for k in ATTRS}
    scores = torch.nn.Parameter(torch.tensor(MASK_INIT).repeat(n, 1))
    extent = scene_extent(cams)
    # position lr: the log-linear decay continued from iteration 7000 of an 8,500-step schedule
    # (TRAINING.md); the rest at the official values
    pos = lambda it: means_lr(it, 8500, extent)  # noqa: E731
    groups = official_groups(params, pos(7000)) + [{"params": [scores], "lr": args.mask_lr, "name": "mask"}]
    opt = torch.optim.Adam(groups, eps=ADAM_EPS)
    gen = torch.Generator().manual_seed(args.seed)
    order: list[int] = []
    hist = []
    t0 = time.perf_counter()
    try:
        from tqdm import tqdm
        bar = tqdm(range(args.steps), desc="mask post-training", mininterval=10)
    except ImportError:  # tqdm is a dependency; keep going without it
        bar = range(args.steps)
    for it in bar:
        if not order:
            order = torch.randperm(len(cams), generator=gen).tolist()
        i = order.pop()
        mask = st_gumbel_mask(scores, gen)
        opac = torch.sigmoid(params["opacity_logits"]) * mask
        img = render(params, opac, cams[i], g0.sh_degree)
        gt = images[i]
        l1 = (img - gt).abs().mean()
        loss = (1 - LAMBDA_DSSIM) * l1 + LAMBDA_DSSIM * (1 - ssim(img, gt) + args.lambda_mask * mask.mean() ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        groups[0]["lr"] = pos(7000 + (it + 1) * 1500 / max(args.steps, 1))
        hist.append((float(loss.detach()), psnr(img, gt), int(mask.detach().sum())))
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{hist[-1][0]:.4f}", drawn=f"{hist[-1][2]:,}", refresh=False)
    train_s = time.perf_counter() - t0
    with torch.no_grad():
        s = scores.detach()
        g = Gaussians(**{k: params[k].detach().clone() for k in ATTRS},
                      extra={"masks_0": s[:, 0].clone(), "masks_1": s[:, 1].clone()})
    out_ply.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out_ply, g)
    last = hist[-min(50, len(hist)):]
    info = {"settings": settings(args, ply), "train_seconds": round(train_s, 1),
            "seconds_per_step": round(train_s / max(args.steps, 1), 3), "threads": torch.get_num_threads(),
            "last50_mean_train_psnr": round(statistics.mean(h[1] for h in last), 3),
            "last50_mean_drawn": round(statistics.mean(h[2] for h in last), 1)}
    (out_ply.parent / "train.json").write_text(json.dumps(info, indent=2))
    return info


def settings(args, ply: Path) -> dict:
    return {"input": str(ply), "steps": args.steps, "mask_lr": args.mask_lr, "lambda_mask": args.lambda_mask,
            "seed": args.seed, "mask_init": list(MASK_INIT), "split": args.split}


def p_keep_histogram(g: Gaussians) -> list[int]:
    p = torch.sigmoid(g.extra["masks_0"].double() - g.extra["masks_1"].double())
    edges = [0.0, 0.05, 0.5, 0.95, 1.0000001]
    return [int(((p >= a) & (p < b)).sum()) for a, b in zip(edges[:-1], edges[1:])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300, help="post-training steps (default 300)")
    ap.add_argument("--mask-lr", type=float, default=0.03, help="Adam lr of the mask scores (default 0.03; official 0.01)")
    ap.add_argument("--lambda-mask", type=float, default=0.1, help="weight of mean(mask)^2 (default 0.1, official post-training)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the view order and training draws")
    ap.add_argument("--seeds", type=int, default=8, help="Gumbel draws scored (seeds 0..K-1; default 8)")
    ap.add_argument("--retrain", action="store_true", help="train again even if a matching file exists")
    ap.add_argument("--threads", type=int, default=2)
    add_split_arg(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ply = FERN / "pretrained/point_cloud/iteration_7000/point_cloud.ply"
    if not ply.is_file():
        sys.exit(f"maskgaussian_masks: {ply} not found (needs ../shared/data beside the repository)")
    scene = load_scene(FERN, resolution=2)
    fit, evals = scene_views(scene, args.split)  # val: post-trained on the fit views, scored on the validation views
    test_imgs = [scene.load_image(c) for c in evals]
    out_ply = OUT / "point_cloud.ply"
    tj = OUT / "train.json"
    info = json.loads(tj.read_text()) if tj.is_file() and out_ply.is_file() else None
    if args.retrain or info is None or info.get("settings") != settings(args, ply):
        print(f"maskgaussian_masks: post-training {ply.name} for {args.steps} steps on {len(fit)} "
              f"views at {fit[0].width}x{fit[0].height}, {torch.get_num_threads()} threads ...")
        info = train(ply, fit, [scene.load_image(c) for c in fit], args, out_ply)
    else:
        print(f"maskgaussian_masks: reusing {out_ply} ({info['train_seconds']} s of training)")
    print(f"maskgaussian_masks: training {info['train_seconds']} s ({info['seconds_per_step']} s/step, "
          f"{info['threads']} threads); last 50 steps: train PSNR {info['last50_mean_train_psnr']:.2f} dB, "
          f"{info['last50_mean_drawn']:.0f} Gaussians drawn per step")

    raw = load_model(out_ply, masks="all")
    n = len(raw)
    hist = p_keep_histogram(raw)
    print(f"p(keep) over {n:,} Gaussians: [0,0.05) {hist[0]:,}  [0.05,0.5) {hist[1]:,}  "
          f"[0.5,0.95) {hist[2]:,}  [0.95,1] {hist[3]:,}")

    def score(g):
        m = evaluate_level(g, evals, test_imgs, None, backend="cpu")
        return m.psnr, m.ssim

    rows = []
    van = read_ply(ply)
    rows.append(("vanilla input (no masks)", len(van), *score(van)))
    for policy in ("argmax", "all"):
        g, mi = apply_masks(raw, policy, path=out_ply)
        rows.append((f"{policy}", mi.kept, *score(g)))
    draws = []
    for seed in range(args.seeds):
        g, mi = apply_masks(raw, "gumbel", seed=seed, path=out_ply)
        draws.append((mi.kept, *score(g)))
        print(f"  gumbel seed {seed}: {mi.kept:,} kept, {draws[-1][1]:.3f} dB", flush=True)
    ks, ps, ss = zip(*draws)
    sd = lambda x: statistics.stdev(x) if len(x) > 1 else 0.0  # noqa: E731

    lines = [f"MaskGaussian-style masks on fern ({n:,} Gaussians, {args.steps} steps, mask lr {args.mask_lr}, "
             f"lambda_mask {args.lambda_mask}); {'validation' if args.split == 'val' else 'test'} views "
             f"{', '.join(c.name for c in evals)} at {evals[0].width}x{evals[0].height}",
             "", "| policy | kept | % | PSNR (dB) | SSIM |", "|---|---:|---:|---:|---:|"]
    for name, k, p, s in rows:
        lines.append(f"| {name} | {k:,} | {100 * k / n:.1f} | {p:.3f} | {s:.4f} |")
    lines.append(f"| gumbel, {len(draws)} seeds: mean +- sd | {statistics.mean(ks):,.0f} +- {sd(ks):.0f} | "
                 f"{100 * statistics.mean(ks) / n:.1f} | {statistics.mean(ps):.3f} +- {sd(ps):.3f} | "
                 f"{statistics.mean(ss):.4f} +- {sd(ss):.4f} |")
    lines.append(f"| gumbel, min..max | {min(ks):,}..{max(ks):,} | | {min(ps):.3f}..{max(ps):.3f} | "
                 f"{min(ss):.4f}..{max(ss):.4f} |")
    lines += ["", f"p(keep): [0,0.05) {hist[0]:,}, [0.05,0.5) {hist[1]:,}, [0.5,0.95) {hist[2]:,}, "
                  f"[0.95,1] {hist[3]:,}"]
    text = "\n".join(lines)
    print(text)
    (OUT / "table.md").write_text(text + "\n")
    print(f"maskgaussian_masks: wrote {OUT / 'table.md'}")


if __name__ == "__main__":
    main()
