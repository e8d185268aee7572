"""Popping (clod_adapter.evaluate.popping): clod-eval's ratio along an s_v sweep through every tier of
a merge tree and along a count-budget sweep."""
from __future__ import annotations

import pytest

from clod_adapter.train import tiers
from clod_adapter.evaluate.popping import popping_ratio
from clod_adapter.io.synthetic import make_cameras
from clod_adapter.lod import tree

from test_tiers import _adapted


@pytest.fixture(scope="module")
def tiered():
    t1 = tiers.attach(_adapted(300, 2), _adapted(60, 3), 2.5, 1.0)
    model = tree.build(tiers.attach(_adapted(1200, 0), t1, 2.0, 1.0), make_cameras(2, 3, 48, 36))
    return model, make_cameras(1, 2, 48, 36)


def test_the_s_v_sweep_runs_through_every_tier(tiered):
    """popping_ratio sweeps s_v from 1 past the coarsest tier's reach (log-spaced), the drawn
    count falls along it, and the ratio is the static switch's jump over the largest step."""
    from clod_adapter.lod.draw import tier_reach

    model, cams = tiered
    p = popping_ratio(model, model.with_sigma_d(None), cams[0], steps=9)
    assert p["s_v"][0] == 1.0 and p["s_v"][-1] == pytest.approx(1.2 * model.lod.max_sv * tier_reach(model))
    assert p["gaussians"][-1] < 0.2 * p["gaussians"][0]
    assert p["ratio"] == pytest.approx(p["discrete_max"] / p["continuous_max"]) and p["continuous_max"] > 0
    assert p["ratio"] > 1  # through every tier, no step as large as one static switch


def test_the_budget_sweep_draws_fewer_gaussians_as_the_budget_falls(tiered):
    """popping_budget_ratio sweeps count budgets from every Gaussian in view down to the lowest
    share: the drawn counts never rise along it and end far below the start, and its ratio is the
    switch's jump over the largest step it measured."""
    from clod_adapter.evaluate.popping import popping_budget_ratio

    model, cams = tiered
    p = popping_budget_ratio(model, model.with_sigma_d(None), cams[0], steps=9, lowest=0.05)
    n = p["gaussians"]
    assert p["s_v"][0] == 1.0 and abs(p["s_v"][-1] - 0.05) < 1e-12
    assert all(b <= a for a, b in zip(n[:-1], n[1:])) and n[-1] < 0.2 * n[0]
    assert p["ratio"] == pytest.approx(p["discrete_max"] / p["continuous_max"])
    with pytest.raises(ValueError, match="lowest"):
        popping_budget_ratio(model, model, cams[0], lowest=1.5)
