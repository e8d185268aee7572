"""clod-export and clod_adapter.export.bake on a tiny synthetic scene (random sigma_d as the adapted model)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import plyfile
import pytest
import torch

from clod_adapter.export import bake as ex
from clod_adapter.io.ply import read_ply, write_ply
from clod_adapter.io.colmap import load_colmap_scene
from clod_adapter.lod.draw import render_lod
from clod_adapter.lod.budget import Budget

from conftest import write_tiny_scene

INRIA = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
         + [f"f_rest_{i}" for i in range(9)]  # SH degree 1 (the tiny scene's)
         + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    scene_dir, ply = write_tiny_scene(root, n=300)
    g = read_ply(ply)
    gen = torch.Generator().manual_seed(0)
    sigma = 0.02 + 0.6 * torch.rand(len(g), generator=gen)
    sigma[:20] = -0.1  # dead Gaussians: never rendered
    adapted = g.with_sigma_d(sigma)
    aply = root / "adapted.ply"
    write_ply(aply, adapted)
    scene = load_colmap_scene(scene_dir)
    return {"root": root, "scene_dir": scene_dir, "plain_ply": ply, "ply": aply, "model": read_ply(aply),
            "scene": scene}


@pytest.fixture(scope="module")
def cli_out(setup):
    from clod_adapter.cli.export import main

    out = setup["root"] / "out"
    rc = main([str(setup["ply"]), "--images", str(setup["scene_dir"]), "-o", str(out), "--s-v", "1.5",
               "--ordered"])
    assert rc == 0
    return out


def minimal_inria_reader(path: Path) -> dict:
    """What a plain INRIA-style loader does: look properties up by name, ignore the rest."""
    v = plyfile.PlyData.read(str(path))["vertex"]
    xyz = np.stack([np.asarray(v[k]) for k in ("x", "y", "z")], axis=1)
    dc = np.stack([np.asarray(v[f"f_dc_{i}"]) for i in range(3)], axis=1)
    rest_names = sorted((p.name for p in v.properties if p.name.startswith("f_rest_")),
                        key=lambda s: int(s.split("_")[-1]))
    rest = np.stack([np.asarray(v[k]) for k in rest_names], axis=1)
    return {"xyz": xyz, "dc": dc, "rest": rest, "opacity": np.asarray(v["opacity"]),
            "scale": np.stack([np.asarray(v[f"scale_{i}"]) for i in range(3)], axis=1),
            "rot": np.stack([np.asarray(v[f"rot_{i}"]) for i in range(4)], axis=1)}


def _rows(path: Path) -> np.ndarray:
    v = plyfile.PlyData.read(str(path))["vertex"].data
    return np.stack([np.asarray(v[n], dtype=np.float32) for n in v.dtype.names], axis=1)


def test_extended_ply_read_by_plain_inria_reader(setup, cli_out):
    m = setup["model"]
    d = minimal_inria_reader(cli_out / "point_cloud_clod.ply")
    np.testing.assert_array_equal(d["xyz"], m.means.numpy())
    np.testing.assert_array_equal(d["dc"], m.sh0.reshape(-1, 3).numpy())
    np.testing.assert_array_equal(d["rest"], m.shN.transpose(1, 2).reshape(len(m), -1).numpy())
    np.testing.assert_array_equal(d["opacity"], m.opacity_logits.numpy())
    np.testing.assert_array_equal(d["rot"], m.quats.numpy())
    names = [p.name for p in plyfile.PlyData.read(str(cli_out / "point_cloud_clod.ply"))["vertex"].properties]
    assert names == INRIA + ["sigma_d"]
    np.testing.assert_array_equal(read_ply(cli_out / "point_cloud_clod.ply").sigma_d.numpy(), m.sigma_d.numpy())


def test_baked_ply_exact_inria_layout_and_kept_set(setup, cli_out):
    path = cli_out / "baked_sv1.5.ply"
    ply = plyfile.PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"]
    assert [p.name for p in ply["vertex"].properties] == INRIA
    assert all(p.val_dtype in ("f4", "float32") or np.dtype(p.val_dtype) == np.float32 for p in ply["vertex"].properties)
    assert ply.byte_order == "<" and not ply.text
    assert path.read_bytes()[:200].find(b"format binary_little_endian 1.0") >= 0
    m, cams = setup["model"], setup["scene"].train  # baked from the training views only (issue 18)
    keep = torch.zeros(len(m), dtype=torch.bool)
    for c in cams:
        keep |= render_lod(m, c, 1.5).mask
    assert 0 < int(keep.sum()) < len(m)
    assert len(ply["vertex"].data) == int(keep.sum())
    np.testing.assert_array_equal(minimal_inria_reader(path)["xyz"], m.means[keep].numpy())
    import json

    rep = json.loads((cli_out / "export.json").read_text())
    assert rep["baked"]["cameras"] == "train" and "psnr_vs_render_lod_train_views" in rep["baked"]


@pytest.mark.slow
def test_bake_opacity_modes_and_budget(setup):
    m, cams = setup["model"], setup["scene"].cameras
    g_auto, info = ex.bake(m, cams, s_v=2.0, return_info=True)
    assert info.chosen in ("original", "mean") and set(info.psnr_vs_lod) == {"original", "mean"}
    assert info.psnr_vs_lod[info.chosen] == max(info.psnr_vs_lod.values())
    assert g_auto.sigma_d is None and len(g_auto) == info.n_kept
    g_orig = ex.bake(m, cams, s_v=2.0, opacity="original")
    g_mean = ex.bake(m, cams, s_v=2.0, opacity="mean")
    assert len(g_orig) == len(g_mean) == len(g_auto)
    assert bool((g_mean.opacity_logits <= g_orig.opacity_logits + 1e-5).all())  # attenuation <= 1
    gb = ex.bake(m, cams, budget=Budget(count=50))  # union of per-view budgets (never below s_v = 1)
    per_view = [int(render_lod(m, c, budget=Budget(count=50)).mask.sum()) for c in cams]
    assert max(per_view) <= len(gb) <= sum(per_view)


def test_ordered_is_permutation_with_sorted_prefixes(setup, cli_out):
    a = _rows(cli_out / "point_cloud_clod.ply")
    b = _rows(cli_out / "ordered.ply")
    assert a.shape == b.shape
    np.testing.assert_array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])])
    om = read_ply(cli_out / "ordered.ply")
    p = ex.persistence(om, setup["scene"].train)  # same set: same d', so same persistence
    assert bool((p[:-1] >= p[1:]).all())
    op = om.opacities
    ties = p[:-1] == p[1:]
    assert bool((op[:-1][ties] >= op[1:][ties]).all())
    perm = ex.importance_order(setup["model"], setup["scene"].train)
    assert sorted(perm.tolist()) == list(range(len(setup["model"])))
    pm = ex.persistence(setup["model"], setup["scene"].train)
    assert bool((pm[:20] < 1).all())  # dead Gaussians: never rendered, ranked after all rendered ones
    pos = torch.empty_like(perm)
    pos[perm] = torch.arange(len(perm))
    assert int(pos[:20].min()) >= int((pm >= 1).sum())
    import json
    rep = json.loads((cli_out / "export.json").read_text())
    rows = rep["ordered"]["prefix_vs_selection_test"]
    assert [r["fraction"] for r in rows] == [1.0, 0.5, 0.25, 0.1]
    assert [r["count"] for r in rows] == [round(f * len(a)) for f in (1.0, 0.5, 0.25, 0.1)]
    assert rep["bytes"]["ordered.ply"] == (cli_out / "ordered.ply").stat().st_size


def test_prune_keeps_everything_rendered_and_the_renders(setup):
    m, scene = setup["model"], setup["scene"]
    pruned, n_drop = ex.prune_never_rendered(m, scene.train, anchor_cameras=scene.cameras)
    assert n_drop >= 20 and len(pruned) == len(m) - n_drop
    kept = {tuple(r) for r in pruned.means.numpy().tolist()}
    for c in scene.train:
        for s in (1.0, 2.0):
            idx = torch.nonzero(render_lod(m, c, s).mask).squeeze(1)
            assert all(tuple(m.means[i].tolist()) in kept for i in idx.tolist())
    for c in scene.cameras:  # d' normalisers kept: identical LoD renders
        torch.testing.assert_close(render_lod(pruned, c, 1.0).image, render_lod(m, c, 1.0).image)


def _degree3(m, scale: float):
    gen = torch.Generator().manual_seed(1)
    return replace(m, shN=scale * torch.randn(len(m), 15, 3, generator=gen))


def test_reduce_sh_keeps_degree_where_it_matters(setup):
    scene = setup["scene"]
    m = _degree3(setup["model"], 0.4)
    imgs = [render_lod(m, c, 1.0).image.clamp(0, 1) for c in scene.train]
    out, info = ex.reduce_sh(m, scene.train, imgs, max_drop_db=0.05)
    assert out.sh_degree == 3 and info["degree_out"] == 3 and info["bytes_saved"] == 0
    assert min(r["drop_db"] for r in info["per_degree"]) > 0.05


def test_reduce_sh_drops_bands_that_are_zero(setup):
    scene = setup["scene"]
    m = _degree3(setup["model"], 1e-7)
    imgs = [scene.load_image(c) for c in scene.train]
    out, info = ex.reduce_sh(m, scene.train, imgs, max_drop_db=0.05)
    assert out.sh_degree == 0 and out.shN.shape[1] == 0
    assert info["bytes_saved"] == 4 * 3 * 15 * len(m)
    assert abs(info["psnr_cost_db"]) <= 0.05


@pytest.mark.slow
def test_cli_prune_and_sh(setup):
    import json

    from clod_adapter.cli.export import main

    out = setup["root"] / "out_prune"
    rc = main([str(setup["ply"]), "--images", str(setup["scene_dir"]), "-o", str(out), "--budget", "0.5",
               "--prune", "--sh-max-drop-db", "0.05"])
    assert rc == 0
    rep = json.loads((out / "export.json").read_text())
    assert rep["prune"]["dropped"] >= 20 and rep["gaussians_out"] == len(setup["model"]) - rep["prune"]["dropped"]
    assert "per_degree" in rep["sh"] and (out / "baked_budget0.5.ply").is_file()
    assert read_ply(out / "point_cloud_clod.ply").sh_degree == rep["sh_degree_out"]


@pytest.mark.parametrize("case", ["missing", "no_sigma", "bad_sv", "bad_budget", "same_as_input", "no_scene",
                                  "bad_sh"])
def test_cli_bad_input(setup, tmp_path, capsys, case):
    from clod_adapter.cli.export import main

    out = tmp_path / "o"
    ply, scene = str(setup["ply"]), str(setup["scene_dir"])
    argv = {
        "missing": [str(tmp_path / "nope.ply"), "--images", scene, "-o", str(out)],
        "no_sigma": [str(setup["plain_ply"]), "--images", scene, "-o", str(out)],
        "bad_sv": [ply, "--images", scene, "-o", str(out), "--s-v", "0.5"],
        "bad_budget": [ply, "--images", scene, "-o", str(out), "--budget", "abc"],
        "same_as_input": [ply, "--images", scene, "-o", str(setup["ply"])],
        "no_scene": [ply, "--images", str(tmp_path / "noscene"), "-o", str(out)],
        "bad_sh": [ply, "--images", scene, "-o", str(out), "--sh-max-drop-db", "-1"],
    }[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("clod-export: error: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == before and not out.exists()


@pytest.mark.parametrize("fmt", ["ply", "spz"])
def test_every_export_format_round_trips(setup, tmp_path, fmt):
    """Each entry of EXPORT_FORMATS writes a file that reads back with the same Gaussians (the
    .spz through gsply, the optional [spz] extra; quantised, so to its precision)."""
    from clod_adapter.jobs.export import EXPORT_FORMATS

    assert set(EXPORT_FORMATS) == {"ply", "spz"}  # a new format needs its case here
    f = EXPORT_FORMATS[fmt]
    m = setup["model"]
    path = tmp_path / f"m{f.suffix}"
    if fmt == "spz":
        gsply = pytest.importorskip("gsply", reason="the .spz writer needs the [spz] extra (gsply)")
        assert f.write(path, m) == path.name
        back = gsply.read_spz(path)
        assert len(back.means) == len(m)
        assert np.abs(np.asarray(back.means) - m.means.numpy()).max() < 1e-3  # 12 fractional bits
        return
    assert f.write(path, m) == path.name
    back = read_ply(path)
    assert torch.equal(back.means, m.means) and torch.equal(back.sigma_d, m.sigma_d)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # atomic: no temporary left
