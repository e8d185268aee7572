"""clod_adapter.lod.draw (and the weighted training budget that uses it): levels and frame cost,
full detail in every view, the s_v frame that projects only what its mask keeps, and in-view shares
(the cost-weighted calibration is tested in test_whole_range.py beside the count one)."""
from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from clod_adapter.lod import rule as lod
from clod_adapter.train.config import AdaptConfig
from clod_adapter.train.loop import weighted_count
from clod_adapter.lod.cost import base_costs
from clod_adapter.io.synthetic import make_cameras, make_ground_truth
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.view import view_lod
from clod_adapter.lod.budget import Budget


@pytest.fixture(scope="module")
def scene():
    gt = make_ground_truth(1500, seed=3)
    cams = make_cameras(3, 2, width=64, height=48)
    g = torch.Generator().manual_seed(1)
    sd = 0.05 + 0.5 * torch.rand(len(gt), generator=g)
    return gt.with_sigma_d(sd), cams


def test_weighted_count_exponent_zero_is_the_count_and_monotone(scene):
    g, cams = scene
    v = view_lod(g, cams[0])
    n = v.n_in_view
    assert weighted_count(v, 0.5, 0.0) == pytest.approx(0.5 * n, abs=1)
    ks = [weighted_count(v, s, 1.0) for s in (0.05, 0.1, 0.3, 0.6, 1.0)]
    assert ks == sorted(ks) and ks[-1] == n
    # with exponent 1 the prefix's cost share fits the budget
    order = torch.sort(-v.critical[v.visible].double(), stable=True).indices
    idx = torch.nonzero(v.visible).squeeze(1)[order]
    c = base_costs(v, idx)  # the costs weighted_count weighs (splat_cost's, to rounding)
    k = weighted_count(v, 0.3, 1.0)
    assert float(c[:k].sum()) <= 0.3 * float(c.sum()) + 1e-6 < float(c[:k + 1].sum())
    with pytest.raises(ValueError):
        AdaptConfig(cost_exponent=1.5)


def test_full_detail_is_the_whole_model_in_every_view(scene):
    g, cams = scene
    # decays so small that most Gaussians have a critical s_v below 1 in these views
    tiny = g.with_sigma_d(torch.full((len(g),), 0.02))
    tiny = replace(tiny, lod=lod.LodSettings(fade="window"))
    for cam in cams[:3]:
        plain = render_lod(tiny.with_sigma_d(None), cam)
        full = render_lod(tiny, cam, 1.0)
        v = view_lod(tiny, cam)
        assert int((v.critical[v.visible] < 1).sum()) > 0.5 * v.n_in_view
        assert full.n_rendered == plain.n_rendered
        assert torch.allclose(full.image, plain.image, atol=1e-6)
        # a budget capped at full detail draws the same
        capped = render_lod(tiny, cam, budget=Budget(in_view=1.0))
        assert torch.allclose(capped.image, plain.image, atol=1e-6)
        # this view's ramp is longer than the fixed one: the rule keeps under half at s_v = 1
        kept1 = float((lod.lod_mask(v.opacities, v.d_norm, v.sigma_d, 1.0) & v.frustum).sum()) / v.n_frustum
        assert v.ramp_s_v == pytest.approx(lod.ramp_s_v(kept1, tiny.lod.max_sv))
        assert v.ramp_s_v > lod.FADE_RAMP_S_V
        # continuous over the ramp: small steps of s_v change the image little, and the LoD
        # rule alone holds from the ramp's end
        prev, steps = full.image, []
        for s in torch.linspace(1.0, v.ramp_s_v, 11)[1:].tolist():
            img = render_lod(tiny, cam, s).image
            steps.append(float((img - prev).abs().mean()))
            prev = img
        assert max(steps) < 0.25 * float((full.image - prev).abs().mean()) + 1e-6
        inside = render_lod(tiny, cam, 0.5 * (1.0 + v.ramp_s_v))  # within the ramp: the whole view drawn
        assert inside.n_rendered == plain.n_rendered
        end = render_lod(tiny, cam, v.ramp_s_v * 1.0001)
        assert end.n_rendered == int(((v.critical > v.ramp_s_v * 1.0001) & v.visible).sum())


def test_ramp_s_v_follows_the_share_kept_at_s_v_1():
    # lod.ramp_s_v: the fixed ramp where the rule keeps every Gaussian at s_v = 1, longer by
    # share^(-2/3) where it keeps less, capped at sqrt(max_sv); full_detail_share over it
    assert lod.ramp_s_v(1.0, 5.0) == pytest.approx(lod.FADE_RAMP_S_V)
    assert lod.ramp_s_v(0.6, 5.0) == pytest.approx(lod.FADE_RAMP_S_V * 0.6 ** (-2 / 3))
    assert lod.ramp_s_v(0.01, 5.0) == pytest.approx(5.0 ** 0.5)
    assert lod.ramp_s_v(0.0, 5.0) == pytest.approx(5.0 ** 0.5)
    assert lod.ramp_s_v(0.5, 1.0) == pytest.approx(lod.FADE_RAMP_S_V)  # untrained range: the fixed ramp
    r = lod.ramp_s_v(0.6, 5.0)
    assert lod.full_detail_share(1.0, r) == 1.0 and lod.full_detail_share(r, r) == 0.0
    assert lod.full_detail_share(r ** 0.5, r) == pytest.approx(0.5)
    assert lod.full_detail_share(lod.FADE_RAMP_S_V, r) > 0.0
    assert lod.full_detail_share(1.05, 1.0) == lod.full_detail_share(1.05)  # never shorter than the fixed ramp


def test_s_v_frame_projects_only_its_mask_and_draws_the_same(scene):
    g, cams = scene
    g = replace(g, lod=lod.LodSettings(fade="window", max_sv=5.0))
    for s in (1.5, 3.0, 8.0):
        for cam in cams[:2]:
            lazy = view_lod(g, cam)
            sel = lazy.select(s)
            assert lazy._proj[2] is not None  # a partial projection
            full = view_lod(g, cam)
            want = lod.lod_mask(full.opacities, full.d_norm, full.sigma_d, s) & full.visible
            assert torch.equal(sel.indices, torch.nonzero(want).squeeze(1)) and torch.equal(sel.mask, want)
            # the same selection when the whole model was projected first (the kept among its visible)
            sel_full = full.select(s)
            assert full._proj[2] is None and torch.equal(sel_full.indices, sel.indices)
            assert torch.equal(sel_full.mask, want) and float(sel_full.eta) == float(sel.eta)
            assert float(sel.eta) == pytest.approx(float((want & full.frustum).sum()) / float(full.frustum.sum()))
            a = render_lod(g, cam, s).image
            b = full.rasterize(full.select(s))[0]
            assert torch.allclose(a, b, atol=1e-6)


def test_a_selection_drawn_after_another_selection_projected(scene):
    # select(3) then select(8) on one view: the second's candidate projection lacks rows of the
    # first; drawing the first then projects the whole model instead of reading wrong rows
    g, cams = scene
    g = replace(g, lod=lod.LodSettings(fade="window", max_sv=5.0))
    cam = cams[0]
    v = view_lod(g, cam)
    sel3 = v.select(3.0)
    sel8 = v.select(8.0)
    assert sel8.indices.numel() < sel3.indices.numel() and v._proj[2] is not None
    img3 = v.rasterize(sel3)[0]
    assert v._proj[2] is None  # fell back to the whole model's projection
    assert torch.allclose(img3, render_lod(g, cam, 3.0).image, atol=1e-6)
    assert torch.allclose(v.rasterize(sel8)[0], render_lod(g, cam, 8.0).image, atol=1e-6)


def test_in_view_share_budgets(scene):
    g, cams = scene
    for cam in cams[:2]:
        v = view_lod(g, cam)
        out = render_lod(g, cam, budget=Budget(in_view=0.25, min_s_v=0.0))
        assert out.n_rendered == round(0.25 * v.n_in_view)
        whole = render_lod(g, cam, budget=Budget(share=0.25, min_s_v=0.0))  # a share of the model
        assert whole.n_rendered == round(0.25 * len(g))


def test_level_grows_to_level_max_below_the_trained_share(scene):
    # below max_sv^-1.5 of the frustum's Gaussians the gains' level goes on growing with ln of
    # the drawn share, up to LodSettings.level_max; 1 holds it there (models trained before it)
    g, cams = scene
    for lm in (1.0, 2.0):
        gl = replace(g, lod=lod.LodSettings(fade="window", max_sv=5.0, level_max=lm))
        for cam in cams[:2]:
            v = view_lod(gl, cam)
            for k in (1, 3, max(1, round(0.05 * v.n_frustum))):
                sel = v.select(budget=Budget(count=k, min_s_v=0.0))
                want = lod.level_of_fraction(sel.indices.numel() / v.n_frustum, 5.0, lm)
                assert sel.level == pytest.approx(want)
                assert 1.0 <= sel.level <= lm
                if lm > 1.0 and k / v.n_frustum < 5.0 ** -3:
                    assert sel.level == 2.0
            out = render_lod(gl, cam, 1e6)  # nothing left: the largest level
            assert out.n_rendered == 0 and out.level == lm
