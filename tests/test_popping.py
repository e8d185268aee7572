"""Popping (clod_adapter.popping): the coarsest tier's window chosen by clod-adapt's rule, and the
config that asks for it."""
from __future__ import annotations

from dataclasses import replace

import pytest

from clod_adapter import tiers
from clod_adapter.camera_lod import tier_chain
from clod_adapter.popping import TAIL_MARGIN, popping_ratio, tail_width, with_coarsest_width
from clod_adapter.synthetic import make_cameras
from clod_adapter.training import AdaptConfig

from test_tiers import _adapted


@pytest.fixture(scope="module")
def chain():
    t1 = tiers.attach(_adapted(300, 2), _adapted(60, 3), 2.5, 1.0)
    model = tiers.attach(_adapted(1200, 0), t1, 2.0, 1.0)
    return model, make_cameras(1, 2, 48, 36)


def test_with_coarsest_width_sets_only_the_last_tier(chain):
    model, _ = chain
    out = with_coarsest_width(model, 3.5)
    before, after = tier_chain(model), tier_chain(out)
    assert [len(t) for t in after] == [len(t) for t in before]
    assert after[-1].lod.fade_width == 3.5 and before[-1].lod.fade_width != 3.5
    assert [t.lod for t in after[:-1]] == [t.lod for t in before[:-1]]


def test_tail_width_takes_the_narrowest_window_that_reaches_the_goal(chain, monkeypatch):
    """The model's own window where it already reaches the goal (one try); otherwise the
    narrowest wider one whose median over the views reaches goal x TAIL_MARGIN, or, where none
    does, the widest (4 here, though 2's median is larger); the returned model carries it."""
    from clod_adapter import popping

    model, cams = chain
    base = model.with_sigma_d(None)
    table = {0.5: 4.0, 1.0: 9.0, 2.0: 14.0, 4.0: 11.0}  # median ratio of each coarsest window
    seen = []

    def fake_ratio(m, b, camera, scores=None, **kw):
        seen.append(camera)
        return {"ratio": table[tier_chain(m)[-1].lod.fade_width] + (cams.index(camera) - 0.5)}

    monkeypatch.setattr(popping, "popping_ratio", fake_ratio)
    assert tier_chain(model)[-1].lod.fade_width == 0.5
    for goal, chosen, tries in ((3.0, 0.5, 1), (10.0, 2.0, 3), (20.0, 4.0, 4), (8.0 / TAIL_MARGIN, 1.0, 2)):
        out, info = tail_width(model, base, cams, goal=goal, widths=(1.0, 2.0, 4.0))
        assert info["chosen"] == chosen and len(info["widths"]) == tries, (goal, info)
        assert tier_chain(out)[-1].lod.fade_width == chosen
        assert [med for _, med, _ in info["widths"]] == [table[w] for w, _, _ in info["widths"]]
    assert seen[:2] == list(cams)


def test_tail_width_stops_at_a_window_of_3_by_default(chain, monkeypatch):
    """Past 3 the window lowered skull's smallest ratio on the validation views (docs/studies.md
    "The coarsest tier's window"): where every wider window would score more and none reaches the
    goal, the default rule tries 0.5, 1, 2 and 3 and keeps 3."""
    from clod_adapter import popping

    model, cams = chain
    monkeypatch.setattr(popping, "popping_ratio",
                        lambda m, b, camera, scores=None, **kw: {"ratio": 2.0 * tier_chain(m)[-1].lod.fade_width})
    out, info = tail_width(model, model.with_sigma_d(None), cams, goal=100.0)
    assert [w for w, _, _ in info["widths"]] == [0.5, 1.0, 2.0, 3.0] and info["chosen"] == 3.0
    assert tier_chain(out)[-1].lod.fade_width == 3.0


def test_the_coarsest_window_changes_the_coarsest_frames(chain):
    """What tail_width chooses between: a wider window draws the coarsest tier's Gaussians with
    other opacities deep in its range (so the frames, and their steps, differ)."""
    from clod_adapter.camera_lod import lod_subset, tier_reach

    model, cams = chain
    s = 0.5 * model.lod.max_sv * tier_reach(model)
    a, b = (lod_subset(with_coarsest_width(model, w), cams[0], s_v=s) for w in (0.5, 4.0))
    assert a.tier_indices[-1] is not None and not (a.opacities.shape == b.opacities.shape and
                                                   bool((a.opacities == b.opacities).all()))
    assert popping_ratio(model, model.with_sigma_d(None), cams[0], steps=9)["ratio"] > 0


def test_tail_width_leaves_a_model_without_tiers_as_it_is(chain):
    model, cams = chain
    plain = replace(model, parents=None, lod=replace(model.lod, tier_s_v=0.0))
    out, info = tail_width(plain, plain.with_sigma_d(None), cams, steps=5)
    assert out is plain and info["chosen"] is None


def test_popping_goal_config():
    assert AdaptConfig().popping_goal == 10.0 and AdaptConfig(schedule="paper").popping_goal == 0.0
    with pytest.raises(ValueError, match="popping_goal"):
        AdaptConfig(popping_goal=-1.0)


def test_count_mix_config():
    """AdaptConfig.count_mix: auto by default, one of off / on / auto, a bad value named."""
    assert AdaptConfig().count_mix == "auto" and AdaptConfig(count_mix="off").count_mix == "off"
    with pytest.raises(ValueError, match="count_mix must be one of off, on, auto"):
        AdaptConfig(count_mix="yes")


def test_the_budget_sweep_draws_fewer_gaussians_as_the_budget_falls(chain):
    """popping_budget_ratio sweeps count budgets from every Gaussian in view down to the lowest
    share: the drawn counts never rise along it and end far below the start, and its ratio is the
    switch's jump over the largest step it measured."""
    from clod_adapter.popping import popping_budget_ratio

    model, cams = chain
    p = popping_budget_ratio(model, model.with_sigma_d(None), cams[0], steps=9, lowest=0.05)
    n = p["gaussians"]
    assert p["s_v"][0] == 1.0 and abs(p["s_v"][-1] - 0.05) < 1e-12
    assert all(b <= a for a, b in zip(n[:-1], n[1:])) and n[-1] < 0.2 * n[0]
    assert p["ratio"] == pytest.approx(p["discrete_max"] / p["continuous_max"])
    with pytest.raises(ValueError, match="lowest"):
        popping_budget_ratio(model, model, cams[0], lowest=1.5)
