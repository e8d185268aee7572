"""``render_lod`` against the numpy implementation of ``docs/lod_rule_plain.md``
(``examples/reference_lod_plain.py``, no ``clod_adapter`` import): the page says all the library does
for a model without merged tiers (a merge tree's: tests/test_tree.py)."""
from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from clod_adapter.lod import rule as lod
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod
from clod_adapter.io.ply import write_ply
from clod_adapter.io.scene import Camera
from clod_adapter.render.dispatch import rasterization
from clod_adapter.io.synthetic import make_cameras, make_ground_truth
from clod_adapter.train.loop import reference_distances

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import reference_lod_plain as ref  # noqa: E402

S_VS = (1.0, 1.04, 1.08, 1.2, 1.5, 2.0, 3.7, 5.0, 12.0, 40.0)


def _model(fade: str, level_max: float, seed: int = 0, fast: float = 0.2):
    """The synthetic scene with a calibrated sigma_d (a random ranking), a share ``fast`` of it
    decaying 10x faster (so views keep less than all at s_v = 1: ramps longer than 1.1) and random
    level gains."""
    g = make_ground_truth(1500, seed=seed)
    cams = make_cameras(2, 3, width=96, height=72)
    gen = torch.Generator().manual_seed(seed)
    n = len(g)
    sd = lod.calibrate_sigma_d(torch.rand(n, generator=gen), g.opacities, reference_distances(g, cams))
    sd = torch.where(torch.rand(n, generator=gen) < fast, sd * 0.1, sd)
    g = dataclasses.replace(
        g.with_sigma_d(sd), opacity_logit_gain=torch.randn(n, generator=gen),
        log_scale_gain=0.3 * torch.randn(n, generator=gen), sh0_gain=0.2 * torch.randn(n, 1, 3, generator=gen),
        lod=lod.LodSettings(max_sv=5.0, fade=fade, level_max=level_max))
    return g, cams


def _inside_camera(width: int = 96, height: int = 72) -> Camera:
    """A camera in the middle of the synthetic box, turned 30 degrees: part of the scene behind it,
    centres across every image edge."""
    a = math.radians(30.0)
    R = torch.tensor([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])
    vm = torch.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ torch.tensor([0.0, 0.3, 5.0])
    f = 0.8 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera.pinhole(vm, K, width, height, name="inside")


def _compare(g, ref_model, cam, s_v):
    v = view_lod(g, cam)
    sel = v.select(s_v)
    _, _, scales, colors = v.drawn_attributes(sel)
    out = ref.draw(ref_model, cam.viewmat.double().numpy(), cam.K.double().numpy(), cam.width, cam.height, s_v)
    where = f"{cam.name} s_v={s_v:g}"
    assert np.array_equal(sel.indices.numpy(), out["ids"]), where
    assert sel.level == pytest.approx(out["level"], abs=1e-9), where
    # opacities: float32 margins against float64 ones (a fade of m / 0.5 near m = 0)
    np.testing.assert_allclose(sel.opacities.detach().numpy(), out["opacities"], rtol=1e-4, atol=2e-5,
                               err_msg=where)
    np.testing.assert_allclose(torch.log(scales).detach().numpy(), out["log_scales"], rtol=1e-5, atol=1e-5,
                               err_msg=where)
    np.testing.assert_allclose(colors[:, 0].detach().numpy(), out["sh0"], rtol=1e-5, atol=1e-5, err_msg=where)
    return sel, out


@pytest.mark.parametrize("fade, level_max", [("window", 1.0), ("window", 2.0), ("eq2", 1.0)])
def test_library_draws_what_the_page_says(tmp_path, fade, level_max):
    ramps, drawn = [], set()
    for fast in (0.0, 0.2):
        g, cams = _model(fade, level_max, fast=fast)
        path = write_ply(tmp_path / f"model{fast}.ply", g)
        m = ref.read_model(path)  # the file as the page describes it
        assert m["settings"]["fade"] == fade and m["settings"]["level_max"] == level_max
        for cam in [*cams, _inside_camera()]:
            v = view_lod(g, cam)
            if fade == "window":
                ramps.append(v.ramp_s_v)
            for s in S_VS:
                sel, _ = _compare(g, m, cam, s)
                drawn.add(sel.indices.numel())
    # the cases the page distinguishes were all reached: ramps longer than 1.1, levels emptied
    assert len(drawn) > 20
    if fade == "window":
        assert max(ramps) > 1.15 and min(ramps) == pytest.approx(1.1)


def test_images_agree_when_the_page_selection_is_rasterised(tmp_path):
    g, cams = _model("window", 1.0, seed=1)
    m = ref.read_model(write_ply(tmp_path / "model.ply", g))
    for cam in (cams[0], _inside_camera()):
        for s in (1.08, 2.0, 5.0):
            out = ref.draw(m, cam.viewmat.double().numpy(), cam.K.double().numpy(), cam.width, cam.height, s)
            ids = torch.from_numpy(out["ids"])
            sh = torch.cat([torch.from_numpy(out["sh0"]).float()[:, None], g.shN.index_select(0, ids)], dim=1)
            img, _, _ = rasterization(g.means.index_select(0, ids), g.quats.index_select(0, ids),
                                      torch.from_numpy(np.exp(out["log_scales"])).float(),
                                      torch.from_numpy(out["opacities"]).float(), sh, cam.viewmat[None], cam.K[None],
                                      cam.width, cam.height, sh_degree=g.sh_degree)
            lib = render_lod(g, cam, s_v=s).image
            assert float((img[0] - lib).abs().max()) < 1e-4, f"{cam.name} s_v={s}"
