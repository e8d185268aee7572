"""Validation views (issue 18): choices are scored on training views held out of the fit, never
on test views (clod_adapter.io.scene.validation_split / holdout_validation)."""
from __future__ import annotations

import random

import pytest

from clod_adapter.io.scene import Scene, holdout_validation, validation_split
from clod_adapter.io.synthetic import make_cameras
from conftest import shared_path


def _names(cams):
    return [c.name for c in cams]


@pytest.mark.parametrize("n", [0, 1, 2, 3, 5, 8, 9, 13, 17, 57, 100])
def test_split_is_deterministic_disjoint_and_covers_train(n):
    cams = make_cameras(1, max(n, 1), width=8, height=6)[:n]
    shuffled = cams[:]
    random.Random(n).shuffle(shuffled)
    fit, val = validation_split(shuffled)
    fit2, val2 = validation_split(cams)
    assert _names(fit) == _names(fit2) and _names(val) == _names(val2)  # order of the input does not matter
    assert not set(_names(fit)) & set(_names(val))
    assert sorted(_names(fit) + _names(val)) == sorted(_names(cams))
    assert _names(fit) == sorted(_names(fit)) and _names(val) == sorted(_names(val))
    if n >= 2:
        assert 1 <= len(val) < n and fit
    else:
        assert val == [] and len(fit) == n


def test_rule_every_8_from_offset_4():
    cams = make_cameras(1, 20, width=8, height=6)
    fit, val = validation_split(cams)
    srt = sorted(_names(cams))
    assert _names(val) == [srt[4], srt[12]]
    _, val = validation_split(cams, every=5, offset=0)
    assert _names(val) == [srt[0], srt[5], srt[10], srt[15]]
    _, val = validation_split(cams[:3])  # fewer than offset + 1 views: the last one
    assert _names(val) == [sorted(_names(cams[:3]))[2]]
    with pytest.raises(ValueError):
        validation_split(cams, every=1)
    with pytest.raises(ValueError):
        validation_split(cams, offset=-1)


def test_skull_has_7_validation_views_and_no_test_view():
    from clod_adapter.io.load import load_scene

    scene = load_scene(shared_path("skull"))
    assert len(scene.train) == 57
    fit, val = validation_split(scene.train, every=8)
    assert len(val) == 7 and len(fit) == 50
    test = set(_names(scene.test))
    assert not test & set(_names(val)) and not test & set(_names(fit))
    held = holdout_validation(scene)
    assert _names(held.train) == _names(fit) and _names(held.test) == _names(val)
    assert held.root == scene.root and held.resolution == scene.resolution
    assert not test & set(_names(held.cameras))


def test_holdout_validation_keeps_the_scene_settings(tmp_path):
    cams = make_cameras(2, 5, width=8, height=6)
    sc = Scene(root=tmp_path, train=cams[:8], test=cams[8:], resolution=2, background=(1.0, 1.0, 1.0))
    held = holdout_validation(sc)
    assert held.background == (1.0, 1.0, 1.0) and held.resolution == 2
    assert len(held.test) == 1 and held.test[0].name == sorted(_names(cams[:8]))[4]
    assert not set(_names(sc.test)) & set(_names(held.cameras))


@pytest.mark.slow
def test_clod_adapt_holdout_val_fits_without_the_validation_views(tmp_path):
    """``clod-adapt --holdout-val`` (the benchmarks' ``--split val``): trained on the fit views,
    scored on the validation views; no test view is used and metrics.json says so."""
    import json

    from clod_adapter.cli.adapt import main as adapt_main
    from conftest import write_tiny_scene
    from clod_adapter.io.load import load_scene

    scene_dir, ply = write_tiny_scene(tmp_path / "src", n=200)
    sc = load_scene(scene_dir)
    fit, val = validation_split(sc.train)
    out = tmp_path / "out"
    code = adapt_main([str(ply), "--images", str(scene_dir), "-o", str(out), "--holdout-val",
                       "--iterations", "2", "--max-sv", "2", "--timing-repeats", "0", "--quiet"])
    assert code == 0
    mj = json.loads((out / "metrics.json").read_text())
    assert mj["holdout_val"] is True and mj["test_views"] == _names(val)
    assert not set(mj["test_views"]) & set(_names(sc.test))
    assert mj["scene_match"]["views"] and set(mj["scene_match"]["views"]) <= set(_names(fit))


def test_benchmarks_scene_views():
    from conftest import REPO
    from benchmarks.common import scene_views, split_suffix

    cams = make_cameras(2, 5, width=8, height=6)
    sc = Scene(root=REPO, train=cams[1:8] + cams[9:], test=[cams[0], cams[8]])
    tr, te = scene_views(sc, "test")
    assert _names(tr) == _names(sc.train) and _names(te) == _names(sc.test)
    fit, val = scene_views(sc, "val")
    assert (fit, val) == validation_split(sc.train)
    assert not set(_names(sc.test)) & set(_names(fit + val))
    assert split_suffix("test") == "" and split_suffix("val") == "_val"
    with pytest.raises(ValueError):
        scene_views(sc, "train")
