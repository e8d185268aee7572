"""Leaving out what a scene does not need first (clod_adapter.train.pruning, clod-adapt --keep-share)."""
import json
from dataclasses import replace

import pytest
import torch

from clod_adapter.train import pruning
from clod_adapter.lod.draw import render_lod
from clod_adapter.io.ply import read_ply
from clod_adapter.io.synthetic import make_cameras, make_ground_truth


@pytest.fixture(scope="module")
def scene():
    gt = make_ground_truth(600, seed=3)
    cams = make_cameras(2, 3, 48, 36)
    with torch.no_grad():
        imgs = [render_lod(gt, c, None).image.clamp(0, 1) for c in cams]
    return gt, cams, imgs


def test_blend_weights_sum_to_the_rendered_alpha(scene):
    """For one view, the weights add up to the rendered alpha's sum (alpha = sum_i alpha_i T_i);
    a Gaussian behind the cameras paints nothing."""
    gt, cams, _ = scene
    behind = replace(gt, means=gt.means.clone())
    behind.means[0] = torch.tensor([0.0, 0.0, -50.0])
    for c in cams[:2]:
        w = pruning.blend_weights(behind, [c])
        with torch.no_grad():
            alpha = render_lod(behind, c, None).alpha
        assert w.dtype == torch.float64 and w.shape == (len(gt),)
        assert float(w.sum()) == pytest.approx(float(alpha.double().sum()), rel=1e-4)
        assert float(w[0]) == 0.0 and bool((w >= 0).all())
    both = pruning.blend_weights(behind, cams[:2])
    assert torch.allclose(both, pruning.blend_weights(behind, cams[:1]) + pruning.blend_weights(behind, cams[1:2]))


def test_leave_out_keeps_the_heaviest_and_recovery_does_not_end_below_its_start(scene):
    gt, cams, imgs = scene
    noisy = replace(gt, sh0=gt.sh0 + 0.15 * torch.randn(gt.sh0.shape, generator=torch.Generator().manual_seed(1)))
    static, info = pruning.leave_out(noisy, cams, imgs, keep_share=0.5, recovery_steps=0)
    w = pruning.blend_weights(noisy, cams)
    assert len(static) == info.kept == 300 and info.input == 600 and info.held_out_psnr == []
    lightest_kept = w[torch.topk(w, 300).indices].min()
    assert float(w[torch.topk(w, 300, largest=False).indices].max()) <= float(lightest_kept)
    rec, info = pruning.leave_out(noisy, cams, imgs, keep_share=0.5, recovery_steps=6)
    assert len(rec) == 300 and info.recovery_steps == 6 and info.held_out_views >= 1
    (s0, p0), (s1, p1) = info.held_out_psnr  # the static cut and the recovery's last step
    assert (s0, s1) == (0, 6) and info.chosen_step == (6 if p1 > p0 else 0)
    static_again, _ = pruning.leave_out(noisy, cams, imgs, keep_share=0.5, recovery_steps=0)
    changed = not torch.equal(rec.means, static_again.means)
    assert changed == (info.chosen_step == 6)  # the recovered model, or the static cut itself
    same, info = pruning.leave_out(noisy, cams, imgs, keep_share=1.0)
    assert len(same) == 600 and info.kept == 600 and same.sigma_d is None
    for bad in (dict(keep_share=0.0), dict(keep_share=1.5), dict(keep_share=0.5, recovery_steps=-1)):
        with pytest.raises(ValueError):
            pruning.leave_out(noisy, cams, imgs, **bad)


def test_adapt_job_leaves_out_first(tiny_model, tmp_path, capfd):
    """clod-adapt --keep-share: the LoD is learned on the kept input (OUT/kept_input.ply), every
    output has the kept count, metrics.json says what was left out and names the input given; a
    resume reuses the kept input; a share out of range is one error line, exit 2, nothing written."""
    from clod_adapter.cli.adapt import main
    from conftest import FAST, err_line

    out = tmp_path / "out"
    args = [str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), *FAST, "--keep-share", "0.5",
            "--recovery-steps", "4", "--faint-share", "0", "-o", str(out)]
    assert main(args) == 0
    m = json.loads((out / "metrics.json").read_text())
    rec = m["leave_out"]
    assert rec["kept"] == 150 and rec["input"] == 300 and m["num_gaussians"] == 150
    assert m["input_ply"] == str(tiny_model["ply"]) and rec["kept_ply"] == str(out / "kept_input.ply")
    assert m["config"]["keep_share"] == 0.5 and set(rec["input_test"]) == {"psnr", "ssim"}
    assert rec["kept_test"]["psnr"] == m["input_model"]["psnr"] != rec["input_test"]["psnr"]
    assert len(read_ply(out / "point_cloud.ply")) == 150 and len(read_ply(out / "kept_input.ply")) == 150
    assert json.loads((out / "leave_out.json").read_text())["kept"] == 150
    stamp = (out / "kept_input.ply").stat().st_mtime_ns
    assert main(args[:-2] + ["-o", str(out), "--resume", "--iterations", "3"]) == 0
    assert (out / "kept_input.ply").stat().st_mtime_ns == stamp  # reused, not left out again
    capfd.readouterr()
    assert json.loads((out / "metrics.json").read_text())["leave_out"]["kept"] == 150
    bad = tmp_path / "bad"
    assert main(args[:-4] + ["--keep-share", "0", "-o", str(bad)]) == 2
    assert "--keep-share must be in (0, 1]" in err_line(capfd) and not bad.exists()


def test_faint_leaves_out_what_paints_under_the_share(scene):
    """pruning.faint: True exactly where the summed blending weight is under share x W x H of one
    view (a Gaussian behind the cameras always); share 0 leaves nothing out; a larger share leaves
    out a superset; when every Gaussian is faint the heaviest stays; a negative share or no view
    raises."""
    gt, cams, _ = scene
    behind = replace(gt, means=gt.means.clone())
    behind.means[0] = torch.tensor([0.0, 0.0, -50.0])
    w = pruning.blend_weights(behind, cams)
    out, px = pruning.faint(behind, cams, 1e-3)
    assert px == pytest.approx(1e-3 * 48 * 36) and out.dtype == torch.bool
    assert torch.equal(out, w < px) and bool(out[0]) and 0 < int(out.sum()) < len(gt)
    none, _ = pruning.faint(behind, cams, 0.0)
    assert not bool(none.any())
    more, _ = pruning.faint(behind, cams, 1e-2)
    assert bool((more | ~out).all()) and int(more.sum()) > int(out.sum())  # a superset
    every, _ = pruning.faint(behind, cams, 1e9)
    assert int((~every).sum()) == 1 and bool(~every[int(torch.argmax(w))])
    for bad in ((behind, cams, -1.0), (behind, [], 1e-5)):
        with pytest.raises(ValueError):
            pruning.faint(*bad)


def test_adapt_job_leaves_out_the_faint(tiny_model, tmp_path, capfd):
    """The default clod-adapt leaves out the faint Gaussians before anything is learned and says so
    (metrics.json ``faint``; every level is compared with the input as given); ``--faint-share 0``
    and the paper's schedule keep every Gaussian."""
    from clod_adapter.cli.adapt import main
    from conftest import FAST

    base = [str(tiny_model["ply"]), "--images", str(tiny_model["scene"]), *FAST]
    assert main(base + ["--faint-share", "0.005", "-o", str(tmp_path / "a")]) == 0
    out = capfd.readouterr().out
    m = json.loads((tmp_path / "a" / "metrics.json").read_text())
    f = m["faint"]
    assert f["input"] == 300 and 0 < f["left_out"] < 300 and m["num_gaussians"] == 300 - f["left_out"]
    assert f["faint_share"] == 0.005 and f["px"] == pytest.approx(0.005 * 64 * 48, abs=1e-3)
    assert f"left out {f['left_out']:,} of 300 Gaussians" in out
    assert m["input_model"]["gaussians"] > m["levels"][0]["gaussians"] - 1e-6  # the input as given is drawn
    assert len(read_ply(tmp_path / "a" / "point_cloud.ply")) == m["num_gaussians"]
    for flags in (["--faint-share", "0"], ["--schedule", "paper"]):
        d = tmp_path / flags[-1]
        assert main(base + flags + ["-o", str(d)]) == 0
        m = json.loads((d / "metrics.json").read_text())
        assert m["faint"] is None and m["num_gaussians"] == 300
