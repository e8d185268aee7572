"""MaskGaussian checkpoints with mask properties (issue 9): the loading policies (argmax, gumbel,
all) of ``clod_adapter.io.load.apply_masks``, and a masked checkpoint that loads, adapts one step
and keeps its mask properties in the output .ply."""
from __future__ import annotations

import json
import math

import numpy as np
import plyfile
import pytest
import torch

from clod_adapter.cli.adapt import main as adapt_main
from clod_adapter.train.config import AdaptConfig
from clod_adapter.gaussians import Gaussians
from clod_adapter.io.load import DEFAULT_MASK_POLICY, MASK_POLICIES, apply_masks, load_model
from clod_adapter.io.ply import PlyFormatError, ply_property_names, read_ply, write_ply
from clod_adapter.jobs.adapt import AdaptOptions, run
from conftest import write_tiny_scene


def _gaussians(n: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(r(n, 3), r(n, 4), r(n, 3) - 3, r(n), r(n, 1, 3), r(n, 3, 3) * 0.5)


def write_masked_ply(path, g: Gaussians, masks: dict[str, np.ndarray]):
    """``g`` as MaskGaussian's ``save_ply`` writes it: the INRIA layout with the mask properties
    right after ``opacity`` (kaikai23/MaskGaussian ``construct_list_of_attributes``)."""
    n = len(g)
    names = ply_property_names(g.sh_degree)
    flat = np.concatenate([g.means.numpy(), np.zeros((n, 3), np.float32), g.sh0.reshape(n, 3).numpy(),
                           g.shN.numpy().transpose(0, 2, 1).reshape(n, -1), g.opacity_logits.numpy()[:, None],
                           g.log_scales.numpy(), g.quats.numpy()], axis=1)
    cols = dict(zip(names, flat.T))
    cols.update(masks)
    i = names.index("opacity") + 1
    order = names[:i] + list(masks) + names[i:]
    data = np.empty(n, dtype=[(k, "<f4") for k in order])
    for k in order:
        data[k] = cols[k]
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(path))
    return path


def _two_groups(n: int):
    """Scores with p(keep) = 0.9 for the first half and 0.1 for the second (masks_1 = 1 + noise)."""
    rng = np.random.default_rng(1)
    m1 = (1.0 + rng.normal(0, 0.5, n)).astype(np.float32)
    d = np.where(np.arange(n) < n // 2, math.log(9.0), -math.log(9.0))
    return (m1 + d).astype(np.float32), m1


# --- policies ------------------------------------------------------------------------------------
def test_policies_on_soft_scores(tmp_path):
    n = 2000
    g = _gaussians(n)
    m0, m1 = _two_groups(n)
    p = write_masked_ply(tmp_path / "soft.ply", g, {"masks_0": m0, "masks_1": m1})
    raw = read_ply(p)
    assert len(raw) == n and list(raw.extra) == ["masks_0", "masks_1"]
    assert DEFAULT_MASK_POLICY in MASK_POLICIES

    # argmax: exactly p(keep) > 0.5, i.e. the first half; the kept Gaussians keep their scores
    a, info = apply_masks(raw, "argmax", path=p)
    first = torch.arange(n) < n // 2
    assert len(a) == n // 2 and torch.equal(a.means, g.means[first])
    assert torch.equal(a.extra["masks_0"], torch.from_numpy(m0)[first])
    assert (info.policy, info.kept, info.total, info.hard, info.seed) == ("argmax", n // 2, n, False, None)
    assert info.describe() == ("masks_0/masks_1 (soft scores): argmax (keep p(keep) > 0.5), "
                               "kept 1,000 of 2,000 Gaussians (50.0 %)")
    assert torch.equal(load_model(p).means, apply_masks(raw, DEFAULT_MASK_POLICY)[0].means)  # "auto"

    # all / ignore: every Gaussian
    for pol in ("all", "ignore"):
        k, info = apply_masks(raw, pol)
        assert len(k) == n and info.policy == "all" and "keep all" in info.describe()
        assert len(load_model(p, masks=pol)) == n

    # gumbel: Bernoulli(p(keep)) per Gaussian, one fixed draw per seed
    def kept(seed, model=raw):
        gg, info = apply_masks(model, "gumbel", seed=seed)
        assert info.seed == seed and f"seed {seed}" in info.describe()
        return torch.isin(g.means[:, 0], gg.means[:, 0])

    k0 = kept(0)
    assert torch.equal(k0, kept(0))
    assert not torch.equal(k0, kept(1))
    assert torch.equal(load_model(p, masks="gumbel", mask_seed=1).means, g.means[kept(1)])
    sd = math.sqrt(n // 2 * 0.9 * 0.1)  # binomial sd of each group's count
    assert abs(int(k0[:n // 2].sum()) - 0.9 * n // 2) < 4 * sd
    assert abs(int(k0[n // 2:].sum()) - 0.1 * n // 2) < 4 * sd
    # log_softmax: adding one constant to both scores changes nothing
    shifted = Gaussians(**raw.tensors(), extra={k: v + 5.0 for k, v in raw.extra.items()})
    assert torch.equal(kept(0, shifted), k0)

    with pytest.raises(ValueError, match="masks must be one of"):
        load_model(p, masks="median")


def test_hard_masks_are_applied_as_drawn(tmp_path):
    n = 90
    g = _gaussians(n, 3)
    on = np.arange(n) % 3 != 0
    p = write_masked_ply(tmp_path / "hard.ply", g, {"masks_0": on.astype(np.float32),
                                                     "masks_1": (~on).astype(np.float32)})
    for pol in ("argmax", "gumbel"):
        k, info = apply_masks(read_ply(p), pol, seed=5)
        assert torch.equal(k.means, g.means[torch.from_numpy(on)])
        assert info.hard and "applied as is" in info.describe()
    assert len(load_model(p, masks="all")) == n


def test_single_mask_logit(tmp_path):
    n = 2000
    g = _gaussians(n, 4)
    logit = np.where(np.arange(n) < n // 2, math.log(9.0), -math.log(9.0)).astype(np.float32)
    p = write_masked_ply(tmp_path / "single.ply", g, {"mask": logit})
    raw = read_ply(p)
    a, info = apply_masks(raw, "argmax")
    assert len(a) == n // 2 and info.source == "mask"
    k, _ = apply_masks(raw, "gumbel", seed=2)
    first = int(torch.isin(g.means[: n // 2, 0], k.means[:, 0]).sum())
    assert abs(first - 0.9 * n // 2) < 4 * math.sqrt(n // 2 * 0.09)
    assert abs(len(k) - n // 2) < 8 * math.sqrt(n * 0.09)


def test_mask_that_keeps_nothing_is_an_error(tmp_path):
    g = _gaussians(20, 5)
    p = write_masked_ply(tmp_path / "none.ply", g, {"masks_0": np.zeros(20, np.float32),
                                                     "masks_1": np.full(20, 3.0, np.float32)})
    with pytest.raises(PlyFormatError, match=r"none\.ply: the mask .*argmax.* keeps no Gaussian"):
        load_model(p)
    assert len(load_model(p, masks="all")) == 20


def test_plain_ply_has_no_mask_info(tmp_path):
    g = _gaussians(10, 6)
    k, info = apply_masks(read_ply(write_ply(tmp_path / "plain.ply", g)), "gumbel")
    assert info is None and len(k) == 10 and k.extra == {}


# --- the job: load, adapt one step, write the mask properties back --------------------------------
@pytest.mark.slow
def test_masked_checkpoint_adapts_and_round_trips_mask_properties(tmp_path, capsys):
    scene, ply = write_tiny_scene(tmp_path, n=300)
    g = read_ply(ply)
    n = len(g)
    rng = np.random.default_rng(0)
    keep = rng.random(n) < 0.8
    m1 = rng.normal(1.0, 0.3, n).astype(np.float32)
    m0 = (m1 + np.where(keep, 1.0, -1.0) * rng.uniform(0.5, 4.0, n)).astype(np.float32)
    masked = write_masked_ply(tmp_path / "masked.ply", g, {"masks_0": m0, "masks_1": m1})
    k = int(keep.sum())
    assert 0 < k < n

    lines = []
    out = tmp_path / "out"
    cfg = AdaptConfig(max_sv=2.0, iterations=1, seed=0, faint_share=0.0)  # every kept row stays, in order
    metrics = run(masked, scene, out, cfg, AdaptOptions(progress=False, log=lines.append, timing_repeats=0, layout="inria"))
    said = [ln for ln in lines if "MaskGaussian masks" in ln]
    assert said == [f"clod-adapt: MaskGaussian masks masks_0/masks_1 (soft scores): argmax (keep p(keep) > 0.5), "
                    f"kept {k:,} of {n:,} Gaussians ({100 * k / n:.1f} %) (--masks argmax|gumbel|all)"]
    assert metrics["num_gaussians"] == k
    assert metrics["input_masks"] == {"policy": "argmax", "source": "masks_0/masks_1", "hard": False,
                                      "kept": k, "total": n, "seed": None, "note": ""}
    assert json.loads((out / "metrics.json").read_text())["input_masks"]["kept"] == k

    # the adapted .ply: the kept Gaussians, in order, with their own scores (bit-exact) and sigma_d
    o = read_ply(out / "point_cloud.ply")
    sel = torch.from_numpy(keep)
    assert len(o) == k and o.sigma_d is not None
    assert list(o.extra) == ["masks_0", "masks_1"]
    assert o.extra["masks_0"].numpy().tobytes() == m0[keep].tobytes()
    assert o.extra["masks_1"].numpy().tobytes() == m1[keep].tobytes()
    assert torch.equal(o.means, g.means[sel])  # base attributes are frozen by default: the same rows
    names = [p.name for p in plyfile.PlyData.read(str(out / "point_cloud.ply"))["vertex"].properties]
    assert names[-2:] == ["masks_0", "masks_1"] and "sigma_d" in names
    # the exact-INRIA copy stays the fixed layout SIBR-style viewers read
    inria = next((out / "point_cloud").glob("iteration_*/point_cloud.ply"))
    assert [p.name for p in plyfile.PlyData.read(str(inria))["vertex"].properties] == ply_property_names(g.sh_degree)
    # re-reading the output applies argmax again: nothing more is dropped
    assert len(load_model(out / "point_cloud.ply")) == k

    # the CLI flag: one Gumbel draw seeded by --seed, and the count it says
    out2 = tmp_path / "out2"
    code = adapt_main([str(masked), "--images", str(scene), "-o", str(out2), "--masks", "gumbel", "--seed", "3",
                       "--iterations", "1", "--max-sv", "2", "--faint-share", "0", "--timing-repeats", "0", "--quiet"])
    assert code == 0
    drawn, info = apply_masks(read_ply(masked), "gumbel", seed=3)
    assert not torch.equal(drawn.means, g.means[torch.from_numpy(keep)])  # a draw, not the argmax
    stdout = capsys.readouterr().out
    assert f"gumbel (one Gumbel draw, seed 3), kept {info.kept:,} of {n:,}" in stdout
    o2 = read_ply(out2 / "point_cloud.ply")
    assert torch.equal(o2.means, drawn.means) and torch.equal(o2.extra["masks_0"], drawn.extra["masks_0"])
    # the draw kept some Gaussians with p(keep) < 0.5; loading the adapted output keeps them all
    assert bool((o2.extra["masks_0"] < o2.extra["masks_1"]).any())
    assert len(load_model(out2 / "point_cloud.ply")) == info.kept
    assert len(load_model(out2 / "point_cloud.ply", masks="argmax")) < info.kept
