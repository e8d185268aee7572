"""The benchmarks' common command line: every script that takes shared inputs also takes any
checkpoint as ``--input NAME=PLY:SCENE[:RES]`` (benchmarks/common.py), and the scripts that
produce docs/results.md say so in their docstring."""
import ast

import pytest

from conftest import REPO

BENCH = REPO / "benchmarks"


@pytest.fixture
def common(monkeypatch):
    from benchmarks import common as mod

    monkeypatch.setattr(mod, "INPUTS", dict(mod.INPUTS))
    monkeypatch.setattr(mod, "LABELS", dict(mod.LABELS))
    return mod


def test_no_script_declares_its_own_inputs_flag():
    """``--inputs`` comes from common.py (add_inputs_args, parse_inputs_args, run_per_input), which
    adds ``--input NAME=PLY:SCENE[:RES]`` beside it."""
    own = [p.relative_to(REPO).as_posix() for p in sorted(BENCH.rglob("*.py"))
           if p.name != "common.py" and '"--inputs"' in p.read_text()]
    assert own == []


def test_input_spec_registers_any_checkpoint(common, tmp_path, monkeypatch):
    import argparse

    monkeypatch.chdir(tmp_path)
    (tmp_path / "c.ply").write_bytes(b"")
    (tmp_path / "d").mkdir()

    ap = argparse.ArgumentParser()
    common.add_inputs_args(ap, ["fern", "skull"])
    assert common.selected_inputs(ap.parse_args([])) == ["fern", "skull"]
    a = ap.parse_args(["--input", "mine=a/b.ply:scene:2", "--input", "two=c.ply:d"])
    assert common.selected_inputs(a) == ["mine", "two"]  # --input alone: only those
    assert common.INPUTS["mine"] == (common.Path("a/b.ply"), common.Path("scene"), 2)
    assert common.resolve_input("two") == (common.Path("c.ply"), common.Path("d"), 1)
    a = ap.parse_args(["--inputs", "skull", "--input", "mine=a/b.ply:scene"])
    assert common.selected_inputs(a) == ["skull", "mine"]
    with pytest.raises(SystemExit, match=r"a/b.ply not found \(--input mine\)"):
        common.resolve_input("mine")


@pytest.mark.parametrize("spec", ["nameless.ply:scene", "x=only.ply", "x=a.ply:s:two", "fern=other.ply:s"])
def test_bad_input_spec_exits_with_one_line(common, spec):
    with pytest.raises(SystemExit) as e:
        common.register_input(spec)
    assert str(e.value).startswith("benchmark: --input") and "\n" not in str(e.value)


def test_unknown_shared_name_exits(common):
    import argparse

    ap = argparse.ArgumentParser()
    common.add_inputs_args(ap, ["fern"])
    with pytest.raises(SystemExit, match="unknown input 'nope'"):
        common.selected_inputs(ap.parse_args(["--inputs", "nope"]))


def test_results_scripts_say_what_they_produce_and_how_long_they_take():
    """The scripts left in benchmarks/ (the studies are in benchmarks/studies/) produce
    docs/results.md: each docstring names it and the time it takes."""
    scripts = sorted(p for p in BENCH.glob("*.py") if p.name not in ("common.py", "__init__.py"))
    assert [p.name for p in scripts] == ["quality_vs_time.py"]
    for p in scripts:
        doc = ast.get_docstring(ast.parse(p.read_text()))
        assert "docs/results.md" in doc and "minutes" in doc, p
    assert len(list((BENCH / "studies").glob("*.py"))) >= 20
    assert not [p.name for p in BENCH.rglob("*.py") if "sys.path.insert(0, str(" in p.read_text()]  # a package


def test_adapt_time_goal_reads_the_whole_jobs_seconds(common):
    """quality_vs_time.py's goal 6 row: ``metrics.json`` ``job_seconds`` against 15 minutes, an
    at-most goal whose margin is the minutes left; a run that did not record it is a miss."""
    import importlib

    qvt_bench = importlib.import_module("benchmarks.quality_vs_time")
    met = qvt_bench.adapt_goal("skull", {"job_seconds": 600.0, "threads": 2})
    assert met["met"] and met["value"] == 10.0 and qvt_bench.margin(met) == 5.0 and "2 threads" in met["goal"]
    late = qvt_bench.adapt_goal("skull", {"job_seconds": 1020.0, "threads": 2})
    assert not late["met"] and qvt_bench.margin(late) == -2.0
    assert not qvt_bench.adapt_goal("skull", {"threads": 2})["met"]
    assert qvt_bench.margin({"value": 3.0, "target": 1.0}) == 2.0  # at-least goals: value - target


def test_ceiling_goal_counts_the_equal_count_points_near_the_ceiling(common):
    """quality_vs_time.py's goal 5 ceiling row: the share of equal-count points with a ceiling
    where the adapted model is within 0.5 dB of it, met at 80 % or more; time cells and points
    without a ceiling do not count, and without any ceiling there is no row."""
    import importlib

    from clod_adapter.evaluate.comparison import Cell

    qvt_bench = importlib.import_module("benchmarks.quality_vs_time")
    pt = lambda db: ("clod", "x", db, 0.5)  # noqa: E731
    cell = lambda kind, ours, ceil: Cell(kind, 0.3, pt(ours), pt(20.0), ours - 20.0,  # noqa: E731
                                         None if ceil is None else ("ceiling", "model=0.3", ceil, 0.5))
    cs = [cell("count", 24.0, 24.4), cell("count", 23.0, 24.0), cell("time", 10.0, 24.0), cell("count", 22.0, None)]
    (row,) = qvt_bench.ceiling_goal("fern", cs)
    assert row["value"] == 0.5 and row["target"] == 0.8 and not row["met"] and "2 points" in row["goal"]
    (near,) = qvt_bench.ceiling_goal("fern", [cell("count", 24.0, 24.4), cell("count", 23.6, 24.0)])
    assert near["met"] and near["value"] == 1.0
    assert qvt_bench.ceiling_goal("fern", [cell("count", 24.0, None)]) == []


def test_behind_line_names_cells_the_adapted_model_cannot_reach(common):
    """quality_vs_time.py's 'where behind' sentence: a cell behind the peer with its margin, a
    cell a peer fills where the adapted model has no level (not 'nowhere'), and 'nowhere' only
    when neither happens."""
    import importlib

    qvt_bench = importlib.import_module("benchmarks.quality_vs_time")
    pt = lambda m, db: {"method": m, "setting": "x", "psnr": db, "time_share": 0.1}  # noqa: E731
    cells = {"a": [{"kind": "time", "share": 0.5, "ours": pt("clod", 20.0), "peer": pt("decimate", 21.0),
                    "margin_db": -1.0},
                   {"kind": "time", "share": 0.1, "ours": None, "peer": pt("opacity", 9.0), "margin_db": None}],
             "b": [{"kind": "time", "share": 0.5, "ours": pt("clod", 22.0), "peer": pt("decimate", 21.0),
                    "margin_db": 1.0}]}
    line = qvt_bench.behind_line([{"name": "a", "label": "A"}, {"name": "b", "label": "B"}], cells)
    assert "A: within 50 % -1.00 dB (decimate); within 10 % no adapted level (opacity 9.00 dB)" in line
    assert "B: nowhere" in line


def test_a_cached_run_is_reused_when_its_settings_match(common, tmp_path, monkeypatch):
    """adapt_cached reuses a run written with today's settings (no ``tier_draw``: merged tiers are
    only drawn as a tree) and one written as a tree with ``tier_draw``, but never one whose tiers
    were drawn as a chain (that one is adapted again)."""
    import json
    from dataclasses import asdict

    from clod_adapter.jobs import adapt as job
    from clod_adapter.train.config import AdaptConfig

    ply, scene = tmp_path / "in.ply", tmp_path / "scene"
    ply.write_bytes(b"ply\n")
    scene.mkdir()
    name = common.register_input(f"cached={ply}:{scene}")
    monkeypatch.setattr(common, "RUNS", tmp_path / "runs")

    def adapted_again(*a, **k):
        raise RuntimeError("adapted again")

    monkeypatch.setattr(job, "run", adapted_again)
    cfg = AdaptConfig()
    for extra, reused in (({}, True), ({"tier_draw": "tree"}, True), ({"tier_draw": "chain"}, False)):
        out = tmp_path / "runs" / name / "default"
        out.mkdir(parents=True, exist_ok=True)
        (out / "metrics.json").write_text(json.dumps({"config": {**asdict(cfg), **extra}, "input_ply": str(ply)}))
        if reused:
            assert common.adapt_cached(name, cfg, "default", log=lambda *a: None) == out / "point_cloud.ply"
        else:
            with pytest.raises(RuntimeError, match="adapted again"):
                common.adapt_cached(name, cfg, "default", log=lambda *a: None)
