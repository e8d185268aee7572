"""The clod-adapt command line runs end to end: --demo, a gsplat checkpoint as the input (its bad
input: tests/test_bad_input.py)."""
import json
import subprocess
import sys

import pytest


from clod_adapter.cli.adapt import main
from conftest import REPO


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, "-m", "clod_adapter.cli.adapt", "--demo", "-o", str(out), "--iterations", "40",
                        "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["faint"]["input"] == 6000 and 0 <= m["faint"]["left_out"] < 6000
    assert len(m["levels"]) == 5 and m["num_gaussians"] == 6000 - m["faint"]["left_out"]
    assert "s_v=5" in r.stdout  # summary table printed
    assert (out / "point_cloud.ply").stat().st_size > 0


@pytest.mark.slow
def test_adapt_from_gsplat_checkpoint(tmp_path, capsys):
    """clod-adapt takes a gsplat ckpt_*.pt (its `splats` dict) as the pretrained model."""
    import torch

    from clod_adapter.io.ply import read_ply
    from conftest import write_tiny_scene

    scene, ply = write_tiny_scene(tmp_path, n=300)
    g = read_ply(ply)
    ckpt = tmp_path / "ckpt_6999.pt"
    torch.save({"step": 6999, "splats": {"means": g.means, "quats": g.quats, "scales": g.log_scales,
                                         "opacities": g.opacity_logits, "sh0": g.sh0, "shN": g.shN}}, ckpt)
    out = tmp_path / "out"
    code = main([str(a) for a in (ckpt, "--images", scene, "-o", out, "--iterations", "2", "--max-sv", "2",
                                  "--faint-share", "0", "--quiet")])
    err = capsys.readouterr().err.strip()
    assert code == 0, err
    adapted = read_ply(out / "point_cloud.ply")
    assert len(adapted) == 300 and adapted.sigma_d is not None
