"""The per-budget ceiling (clod_adapter.train.finetune): the recovery schedule, its loss history and
convergence check, and the choice of the start subset on validation views."""
from __future__ import annotations

import math

import pytest
import torch

from clod_adapter.train.official import OFFICIAL_LR, scene_extent
from clod_adapter.train.finetune import (RECOVERY_DECAY, RECOVERY_ITERATIONS, FinetuneOptions, best_start, convergence,
                                         finetune_subset, means_lr)
from clod_adapter.io.scene import validation_split
from clod_adapter.train.losses import render_loss
from clod_adapter.io.synthetic import make_cameras, make_ground_truth, perturb
from clod_adapter.lod.draw import render_lod
from conftest import render_views


@pytest.fixture(scope="module")
def tiny():
    gt = make_ground_truth(900, seed=3)
    cams = make_cameras(2, 3, width=64, height=48)
    return gt, perturb(gt, 5), cams, render_views(gt, cams)


@torch.no_grad()
def _train_loss(model, cams, imgs):
    return sum(float(render_loss(render_lod(model, c, None).image, gt)) for c, gt in zip(cams, imgs)) / len(cams)


def test_recovery_position_lr_schedule():
    final = OFFICIAL_LR["means"][1]
    ext, n = 2.5, 1000
    assert RECOVERY_DECAY == 0.01 and RECOVERY_ITERATIONS == 5000
    assert math.isclose(means_lr(0, n, ext), final * ext, rel_tol=1e-12)  # the official final rate
    assert math.isclose(means_lr(n, n, ext), 0.01 * final * ext, rel_tol=1e-12)
    assert math.isclose(means_lr(n // 2, n, ext), 0.1 * final * ext, rel_tol=1e-12)  # log-linear
    assert math.isclose(means_lr(n + 50, n, ext), 0.01 * final * ext, rel_tol=1e-12)  # clamped
    lrs = [means_lr(i, n, ext) for i in range(0, n + 1, 50)]
    assert all(a > b for a, b in zip(lrs, lrs[1:]))
    assert math.isclose(means_lr(0, n, ext, lr_scale=0.5), 0.5 * final * ext, rel_tol=1e-12)
    assert math.isclose(means_lr(n, n, ext, decay=0.1), 0.1 * final * ext, rel_tol=1e-12)
    # the first version's schedule: restarts at the official initial rate
    assert math.isclose(means_lr(0, n, ext, schedule="official"), OFFICIAL_LR["means"][0] * ext, rel_tol=1e-12)
    assert math.isclose(means_lr(n, n, ext, schedule="official"), final * ext, rel_tol=1e-12)
    with pytest.raises(ValueError):
        means_lr(0, n, ext, schedule="cosine")


def test_convergence_check():
    c = convergence([1.0] * 80 + [0.5] * 10 + [0.5] * 10)
    assert c["window"] == 10 and c["last"] == 0.5 and c["previous"] == 0.5
    assert c["relative_change"] == 0.0 and c["converged"]
    c = convergence([1.0] * 90 + [0.8] * 10)
    assert math.isclose(c["relative_change"], -0.2) and not c["converged"]
    c = convergence([1.0])
    assert c["window"] == 1 and c["last"] == 1.0 and c["previous"] is None and not c["converged"]
    assert convergence([])["last"] is None


def test_recovery_lowers_training_loss_and_records_history(tiny):
    _, model, cams, imgs = tiny
    steps = 60
    before = _train_loss(model, cams, imgs)
    with torch.no_grad():  # a caller's no_grad (clod-eval) does not stop training
        out, info = finetune_subset(model, cams, imgs, FinetuneOptions(iterations=steps), return_info=True)
    after = _train_loss(out, cams, imgs)
    assert after < 0.9 * before, (before, after)
    assert info.schedule == "recovery" and info.iterations == steps
    assert len(info.loss) == steps and all(math.isfinite(x) for x in info.loss)
    ext = scene_extent(cams)
    assert math.isclose(info.means_lr_first, OFFICIAL_LR["means"][1] * ext, rel_tol=1e-9)
    assert math.isclose(info.means_lr_last, means_lr(steps - 1, steps, ext), rel_tol=1e-9)
    assert info.convergence == convergence(info.loss) and info.convergence["window"] == 6
    assert sum(info.loss[-10:]) < sum(info.loss[:10])
    assert set(info.to_dict()) >= {"loss", "convergence", "schedule"}
    # positions move far less than under the old schedule (which restarted at 1.6e-4 x extent)
    old = finetune_subset(model, cams, imgs, FinetuneOptions(iterations=steps, schedule="official"))
    assert isinstance(old, type(out))
    moved_new = (out.means - model.means).norm(dim=1).mean()
    moved_old = (old.means - model.means).norm(dim=1).mean()
    assert moved_new < 0.2 * moved_old


def test_best_start_picks_the_higher_validation_psnr(tiny):
    gt, model, cams, _ = tiny
    fit, val = validation_split(cams)
    assert val and not {c.name for c in val} & {c.name for c in fit}
    val_imgs = render_views(gt, val)
    good, bad, half = gt, model, gt.subset(torch.arange(0, len(gt), 2))
    for cands in ({"bad": bad, "half": half, "good": good}, {"good": good, "bad": bad, "half": half}):
        name, g, scores = best_start(cands, val, val_imgs, return_scores=True)
        assert name == "good" and g is good and scores["good"] > scores["bad"] > scores["half"]
    assert best_start({"only": bad}, val, val_imgs)[0] == "only"
    with pytest.raises(ValueError):
        best_start({}, val, val_imgs)
    with pytest.raises(ValueError):
        best_start({"good": good}, [], [])


def test_finetune_shows_progress_lines_in_a_log(tiny, capsys):
    """A long ceiling fine-tune (clod-eval --dlod-iterations 5000: 20 minutes) prints a line every
    10 % of its steps when stderr is a log, not a terminal."""
    _, model, cams, imgs = tiny
    finetune_subset(model, cams, imgs, FinetuneOptions(iterations=10), progress="dlod test")
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("dlod test:")]
    assert len(lines) >= 10 and lines[-1].startswith("dlod test: 10/10 step"), lines
    finetune_subset(model, cams, imgs, FinetuneOptions(iterations=3))
    assert "dlod" not in capsys.readouterr().err


def test_finetune_keeps_the_checkpoint_best_on_validation_views(tiny):
    """Trained towards wrong (black) images, every step lowers the PSNR on the true validation
    views: the start is returned unchanged. Trained towards the true images, a later checkpoint
    wins and the returned model scores what the history says."""
    from clod_adapter.metrics import psnr

    gt, model, cams, imgs = tiny
    fit, val = cams[:4], cams[4:]
    val_imgs = imgs[4:]
    black = [torch.zeros_like(im) for im in imgs[:4]]

    def val_psnr(m):
        with torch.no_grad():
            return sum(psnr(render_lod(m, c, None).image, t, cap=True) for c, t in zip(val, val_imgs)) / len(val)

    out, info = finetune_subset(model, fit, black, FinetuneOptions(iterations=20, val_every=5), val=(val, val_imgs),
                                return_info=True)
    assert [s for s, _ in info.val_psnr] == [0, 5, 10, 15, 20]
    assert info.best_step == 0 and info.val_psnr[-1][1] < info.val_psnr[0][1] - 1.0
    assert torch.equal(out.means, model.means) and torch.equal(out.opacity_logits, model.opacity_logits)
    out, info = finetune_subset(model, fit, imgs[:4], FinetuneOptions(iterations=40, val_every=10),
                                val=(val, val_imgs), return_info=True)
    best = max(p for _, p in info.val_psnr)
    assert info.best_step > 0 and math.isclose(val_psnr(out), best, abs_tol=1e-4)
