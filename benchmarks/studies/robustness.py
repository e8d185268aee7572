"""The CLoD-GS paper's robustness experiment: CLoD on a MaskGaussian checkpoint.

For each input model (the vanilla fern checkpoint and the MaskGaussian-pruned one, 19,383
Gaussians) and each max_sv in {1, 3, 5, 7}: ``clod-adapt`` with its defaults, then PSNR / SSIM /
LPIPS and Gaussians drawn along the s_v sweep and at budgets from 100 % to 3.5 %, beside the input
model cut to the same budgets by opacity ranking, LightGaussian significance and splat-transform's
merging decimator. Writes ``runs/bench/robustness.csv``, ``robustness.md`` and ``robustness.png``
(the paper's form: PSNR vs Gaussians drawn, one curve per max_sv plus the static cuts, one panel
per input model):

    python -m benchmarks.studies.robustness

It shares adaptations with max_sv_sweep.py and whole_range.py (runs/bench/, same settings).
A report, not a choice: scored on the test views by default (``--split val`` for the
validation views).
"""
from benchmarks.studies.max_sv_sweep import main

if __name__ == "__main__":
    main(default_inputs=("fern", "maskgaussian"), out_name="robustness", default_split="test")
