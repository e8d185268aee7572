"""The quality-against-frame-time comparison (clod_adapter.evaluate.comparison): its cells and verdict,
clod-eval and benchmarks/quality_vs_time.py giving the same cells, and README's results table
held to the generated docs/results.json and docs/results.md."""
import json
import math
import statistics

import pytest

from clod_adapter.evaluate import comparison as qvt
from conftest import REPO


def _setting(method, setting, psnr, ms, drawn):
    s = qvt.Setting(method, setting, [], 100)
    s.psnr, s.ms, s.ms_min, s.ms_max, s.drawn = psnr, ms, ms, ms, [drawn]
    return s


def _comparison():
    st = [_setting("input", "full", 30.0, 100.0, 1000),
          _setting("clod", "s_v=1", 29.95, 102.0, 1000), _setting("clod", "s_v=2", 28.0, 45.0, 400),
          _setting("clod", "s_v=5", 22.0, 20.0, 100),
          _setting("decimate", "model=0.5", 27.0, 48.0, 500), _setting("decimate", "model=0.15", 24.0, 18.0, 150),
          _setting("lightgaussian", "in_view=0.1", 20.0, 9.0, 100),
          _setting("clod", "match:decimate:model=0.15", 25.5, 21.0, 150),
          _setting("opacity", "match:decimate:model=0.15", 23.0, 17.0, 150)]
    return qvt.Comparison(st, [1000], max_sv=5.0, full_ratio=1.02, merge_run=True)


def test_cells_pick_the_best_within_each_time_and_the_best_peer_at_each_count():
    cs = qvt.cells(_comparison())
    full, t75, t50, t25, t10, count = cs
    assert (full.kind, full.ours[1], round(full.margin_db, 2)) == ("full", "s_v=1", -0.05)
    assert (t50.ours[1], t50.peer[1], round(t50.margin_db, 2)) == ("s_v=2", "model=0.5", 1.0)
    # within 25 %: ours s_v=5 (20 ms) against the decimator at 18 ms
    assert (t25.ours[1], t25.peer[1], round(t25.margin_db, 2)) == ("s_v=5", "model=0.15", -2.0)
    assert t10.ours is None and t10.peer[0] == "lightgaussian" and t10.margin_db == -math.inf
    # at the decimator's counts: the best of the decimator and the rankings drawn there
    assert (count.kind, count.share, count.peer[0], round(count.margin_db, 2)) == ("count", 0.15, "decimate", 1.5)
    assert [c["kind"] for c in qvt.cells_json(cs)] == ["full", "time", "time", "time", "time", "count"]
    assert qvt.cells_json(cs)[4]["margin_db"] is None  # -inf is not JSON
    # a count cell names the budget (the decimator's share), also where the adapted model draws fewer
    comp = _comparison()
    comp.settings[7] = _setting("clod", "match:decimate:model=0.15", 25.5, 15.0, 90)
    assert qvt.cells(comp)[-1].share == 0.15 and comp.in_view_share(comp.settings[7]) == 0.09


def test_cost_follows_reads_the_steps_of_both_sweeps():
    comp = _comparison()
    comp.settings += [_setting("clod", "in_view=1", 29.95, 102.0, 1000), _setting("clod", "in_view=0.5", 28.0, 60.0, 500),
                      _setting("clod", "in_view=0.1", 24.0, 66.0, 100)]
    c = qvt.cost_follows(comp)
    assert c["level_step"] == pytest.approx(20.0 / 45.0)  # s_v 1 -> 2 -> 5: never rises
    assert c["budget_step"] == pytest.approx(66.0 / 60.0)  # the 10 % frame over the 50 % one
    assert c["over_input"] == pytest.approx(1.02)
    assert c["count_ratio"] == pytest.approx(21.0 / 18.0)


def test_cost_follows_pairs_the_rounds_when_the_sweeps_were_timed_alone():
    """Round 2 ran slow for every setting: the medians of two frames read apart put a rise where
    the per-round ratios, paired, have none."""
    comp = _comparison()
    comp.sweep_rounds = {"input": [100.0, 100.0, 130.0], "s_v=1": [99.0, 99.0, 129.0],
                         "s_v=2": [45.0, 50.0, 58.0], "s_v=5": [40.0, 44.0, 52.0]}
    c = qvt.cost_follows(comp)
    assert c["level_step"] == pytest.approx(max(statistics.median([45 / 99, 50 / 99, 58 / 129]),
                                                statistics.median([40 / 45, 44 / 50, 52 / 58]),
                                                statistics.median([40 / 99, 44 / 99, 52 / 129])))
    assert c["level_step"] < 1.0
    assert c["over_input"] == pytest.approx(0.99)
    assert c["count_ratio"] == pytest.approx(21.0 / 18.0)  # the pair not timed alone: the run's medians
    comp.sweep_rounds.update({"match:decimate:model=0.15": [21.0, 17.0, 30.0], "decimate:model=0.15": [20.0, 18.0, 20.0]})
    # paired: the median of 1.05, 0.94, 1.5, not 21 / 18
    assert qvt.cost_follows(comp)["count_ratio"] == pytest.approx(1.05)
    assert qvt.paired_worst_step([[10.0, 10.0], [9.0, 12.0], [11.0, 11.0]]) == pytest.approx(1.1)


def test_sweep_times_times_the_input_both_sweeps_and_the_equal_count_pairs_alone():
    calls = []

    class _R:
        select_ms, raster_ms = 0.0, 1.0

    def render(name):
        def f():
            calls.append(name)
            return None, 1, 2.0
        return f

    st = [qvt.Setting("input", "full", [render("input")], 1), qvt.Setting("clod", "s_v=1", [render("s_v=1")], 1),
          qvt.Setting("clod", "in_view=0.5", [render("in_view=0.5")], 1),
          qvt.Setting("decimate", "model=0.5", [render("decimate")], 1),
          qvt.Setting("decimate_adaptive", "model=0.5", [render("decimate_adaptive")], 1),
          qvt.Setting("decimate", "model=0.3", [render("decimate 0.3")], 1),
          qvt.Setting("clod", "match:decimate_adaptive:model=0.5", [render("match")], 1),
          qvt.Setting("opacity", "match:decimate_adaptive:model=0.5", [render("opacity")], 1)]
    comp = qvt.Comparison(st, [10], max_sv=5.0)
    rr = qvt.sweep_times(comp, repeats=3)
    assert set(rr) == {"input", "s_v=1", "in_view=0.5", "match:decimate_adaptive:model=0.5",
                       "decimate_adaptive:model=0.5"}
    assert all(len(v) == 3 and all(x == pytest.approx(2.0) for x in v) for v in rr.values())
    assert calls.count("input") == 4 and calls.count("match") == 4  # a warm-up round, then 3
    assert not {"decimate", "decimate 0.3", "opacity"} & set(calls)  # no equal-count pair of theirs


def test_verdict_says_where_ours_is_ahead_and_by_how_much():
    v = qvt.verdict(_comparison())
    assert "102 % of its frame time" in v
    assert "ahead within 75 % (+1.00 dB" in v and "within 50 % (+1.00 dB" in v
    assert "behind within 25 % (-2.00 dB" in v and "within 10 % (no level that fast" in v
    assert "ahead at 1 of 1: 15 % in view +1.50 dB against decimate" in v
    md = qvt.cells_markdown(qvt.cells(_comparison()))
    assert md.count("\n") == 1 + 6 and "| +1.50 |" in md


def test_a_ceiling_below_a_target_lowers_it_and_the_goal_says_so():
    """Goal 4: the per-budget ceiling (one fine-tuned model per decimator share) caps a goal at
    ceiling - 0.2 dB where it is below the target; a ceiling above leaves the target alone."""
    comp = _comparison()
    comp.settings.append(_setting("ceiling", "model=0.15", 25.6, 19.0, 150))
    comp.settings.append(_setting("ceiling", "model=0.5", 27.3, 47.0, 500))
    cs = qvt.cells(comp)
    count = cs[-1]
    assert count.ceiling[:3] == ("ceiling", "model=0.15", 25.6)
    assert cs[2].ceiling[1] == "model=0.5" and cs[4].ceiling is None  # within 50 %; nothing within 10 %
    rows = {r["goal"].split(" >= ")[0]: r for r in _bench().goals("x", comp, cs)}
    # within 50 %: peer 27.0 + 1 = 28.0 > ceiling 27.3 -> 27.1, ours 28.0 meets it
    assert rows["within 50 % time"]["rule"] == "ceiling - 0.2" and math.isclose(rows["within 50 % time"]["target"], 27.1)
    # equal count: peer 24.0 + 0.5 = 24.5 < ceiling 25.6: the peer rule stays
    r = rows["equal count 15.0 % in view"]
    assert r["rule"] == "peer + 0.5" and math.isclose(r["target"], 24.5) and r["met"]
    assert rows["within 75 % time"]["rule"] == "ceiling - 0.2"  # input - 0.1 = 29.9 > 27.3
    assert "ceiling: setting" in qvt.cells_markdown(cs) and qvt.cells_json(cs)[-1]["ceiling"]["psnr"] == 25.6


def test_a_ceiling_model_is_kept_and_read_back_only_while_its_record_matches(tmp_path):
    """The per-budget ceiling's cache: a fitted model is written with its record and read back
    bit-exact for the same starts, views and steps; any other key, or a missing record, fits anew."""
    import torch

    from clod_adapter.evaluate.ceiling_cache import cached_ceiling, store_ceiling
    from clod_adapter.io.synthetic import make_ground_truth

    g = make_ground_truth(50, seed=3)
    key = {"steps": 600, "starts": {"decimate": 50, "lightgaussian": 50}, "input": 200, "fit_views": 17,
           "val_views": 2, "background": [0.0, 0.0, 0.0]}
    cache = tmp_path / "ceiling"
    assert cached_ceiling(cache, 0.3, key) is None  # nothing kept yet
    store_ceiling(cache, 0.3, g, {**key, "start": "decimate", "best_step": 500})
    back, info = cached_ceiling(cache, 0.3, key)
    assert (info["start"], info["best_step"]) == ("decimate", 500)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN"):
        assert torch.equal(getattr(back, name), getattr(g, name).float()), name
    assert cached_ceiling(cache, 0.15, key) is None  # another share
    assert cached_ceiling(cache, 0.3, {**key, "steps": 300}) is None
    assert cached_ceiling(cache, 0.3, {**key, "starts": {"decimate": 49, "lightgaussian": 50}}) is None
    (cache / "model=0.3.json").unlink()
    assert cached_ceiling(cache, 0.3, key) is None


def _bench():
    from benchmarks import quality_vs_time as bench

    return bench


def test_readme_results_table_is_the_generated_one():
    """README's table equals the one docs/results.json gives, and docs/results.md holds it too."""
    bench = _bench()
    res = json.loads((REPO / "docs" / "results.json").read_text())
    want = bench.results_table(res["table"], res["cells"])

    def block(path):
        s = path.read_text()
        assert s.count(bench.BEGIN) == 1 and s.count(bench.END) == 1, f"{path}: results-table markers"
        return s[s.index(bench.BEGIN) + len(bench.BEGIN):s.index(bench.END)].strip()

    assert block(REPO / "README.md") == want, "README's results table differs from docs/results.json: " \
                                              "python -m benchmarks.quality_vs_time --docs writes both"
    assert block(REPO / "docs" / "results.md") == want
    assert {r["name"] for r in res["table"]} == {"fern", "maskgaussian", "skull"}
    for r in res["table"]:  # the table's cells are the cells of the comparison
        cells = {round(c["share"], 6): c for c in res["cells"][r["name"]] if c["kind"] == "time"}
        for sh in bench.TABLE_SHARES:
            c, w = cells[sh], r["within"][f"{sh:g}"]
            assert w["ours"] == (c["ours"]["psnr"] if c["ours"] else None)
            assert w["peer"] == (c["peer"]["psnr"] if c["peer"] else None)


@pytest.mark.slow
def test_clod_eval_gives_the_benchmarks_cells(tmp_path, monkeypatch, capsys):
    """On the demo scene, clod-eval and benchmarks/quality_vs_time.py compare the same settings
    and say the same cells. Both time every render through qvt.timed_call; here it reads a
    render's time from its drawn count, so the two runs' times, and so their cells, are equal
    exactly (wall time would differ between two runs). clod-eval's progress ends at 90-100 % of
    its total (qvt.n_renders counts the comparison's renders), never past it."""
    from clod_adapter.cli.eval import main as eval_main
    from clod_adapter.io.splat_transform import find_splat_transform

    if find_splat_transform() is None:
        pytest.skip("splat-transform not installed (`npm ci`): the comparison's decimators")
    monkeypatch.setattr(qvt, "timed_call", lambda fn: (lambda out: (out, 1.0 + 0.01 * out.n_rendered))(fn()))
    bench = _bench()
    monkeypatch.setattr(bench.common, "RUNS", bench.common.RUNS)  # restored after the test
    assert bench.main(["--inputs", "demo", "--config", "iterations=40", "--repeats", "1", "--no-lpips",
                       "--ceiling-steps", "0",
                       "--runs", str(tmp_path / "bench"), "--threads", "2"]) in (0, 1)
    run = tmp_path / "bench" / "quality_vs_time" / "iterations-40"
    want = json.loads((run / "demo.json").read_text())["cells"]
    demo = tmp_path / "bench" / "demo_input"
    code = eval_main([str(tmp_path / "bench" / "demo" / "iterations-40"), "--images", str(demo / "scene"),
                      "--pretrained", str(demo / "pretrained" / "point_cloud.ply"), "--no-lpips",
                      "--timing-repeats", "1", "--dlod-iterations", "0", "--sv-steps", "3", "--budgets", "1,0.25",
                      "-o", str(tmp_path / "report")])
    assert code == 0
    bar = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("clod-eval: ") and " render (" in ln]
    n, total = (int(x) for x in bar[-1].split()[1].split("/"))
    assert 0.9 * total <= n <= total and not any("/?" in ln for ln in bar)
    rep = json.loads((tmp_path / "report" / "report.json").read_text())["quality_vs_time"]
    assert rep["cells"] == want
    assert len([c for c in want if c["kind"] == "count"]) >= 2 and rep["decimators_run"]
    md = (tmp_path / "report" / "report.md").read_text()
    assert md.startswith("## Quality against frame time\n\n" + rep["verdict"])
    head = (tmp_path / "report" / "quality_vs_time.csv").read_text().splitlines()[0]
    assert head == ",".join(qvt.CSV_COLUMNS) and (tmp_path / "report" / "quality_vs_time.png").stat().st_size > 0
