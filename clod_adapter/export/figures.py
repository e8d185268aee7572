"""Figures and captioned picture sheets people look at: the LoD strip (ground truth beside the
renders at several ``s_v``), the training curve, and captioned panels (``clod-render``,
``examples/render_hook.py``). Written as PNG, atomically."""
from __future__ import annotations

from pathlib import Path

import torch

from ..io.atomic import atomic_save
from ..lod.draw import render_lod


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1 with FreeType
    except TypeError:
        return ImageFont.load_default()


def label_panels(panels, captions, min_width: int = 240):
    """Put images side by side, each with its caption in a band *below* it (never over the
    picture). Images narrower than ``min_width`` px are enlarged (nearest neighbour, integer
    factor) so the captions stay readable. ``panels``: [H, W, 3] float tensors/arrays in [0, 1]
    or uint8 arrays; ``captions``: one string per panel (may contain newlines). Returns a PIL
    image."""
    import numpy as np
    from PIL import Image, ImageDraw

    ims = []
    for p in panels:
        a = p.detach().clamp(0, 1).cpu().numpy() if hasattr(p, "detach") else np.asarray(p)
        if a.dtype != np.uint8:
            a = (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
        ims.append(Image.fromarray(np.ascontiguousarray(a)))
    w, h = ims[0].size
    k = max(1, -(-min_width // max(w, 1)))
    if k > 1:
        ims = [im.resize((w * k, h * k), Image.Resampling.NEAREST) for im in ims]
        w, h = w * k, h * k
    lines = max(len(c.split("\n")) for c in captions)
    size = int(min(max(w / 14, 11), 26))
    font = _font(size)
    band = lines * (size + 4) + 8
    gap = 4
    sheet = Image.new("RGB", (len(ims) * w + (len(ims) - 1) * gap, h + band), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for i, (im, cap) in enumerate(zip(ims, captions)):
        x = i * (w + gap)
        sheet.paste(im, (x, 0))
        draw.multiline_text((x + 4, h + 4), cap, fill=(0, 0, 0), font=font, spacing=4)
    return sheet


def write_strip(path: Path, gaussians, camera, s_vs, background, gt=None) -> None:
    """Render ``camera`` at each ``s_v`` and write the images side by side as a PNG, the ground
    truth ``gt`` ([H, W, 3] in [0, 1], optional) first; each panel is captioned below with its
    s_v and the Gaussians rendered (count and % of the model)."""
    panels, caps = [], []
    if gt is not None:
        panels.append(gt)
        caps.append(f"ground truth\n{camera.name}")
    n = max(len(gaussians), 1)
    with torch.no_grad():
        for s in s_vs:
            out = render_lod(gaussians, camera, s, background=background)
            panels.append(out.image)
            caps.append(f"s_v = {s:g}\n{out.n_rendered:,} G ({100 * out.n_rendered / n:.0f} %)")
    sheet = label_panels(panels, caps)
    atomic_save(path, lambda tmp: sheet.save(tmp, format="PNG"))


def write_training_plot(path: Path, history: dict, max_sv: float, views_per_step: int = 1) -> None:
    """``training.png``: loss, PSNR of the training view and rendered fraction against the step,
    from ``AdaptState.history`` (per step ``loss``, ``psnr``, ``eta`` at the sampled ``s_v``).
    PSNR and fraction are drawn per step coloured by that step's s_v, with the running mean of
    the steps near full detail (s_v <= 1 + 0.1 (max_sv - 1)) as a line: the loop renders one
    random s_v per view, so this is its closest record of "PSNR at s_v = 1". The history holds
    one record per view; with ``views_per_step`` > 1 they are placed at fractional steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    loss = np.asarray(history.get("loss", []), dtype=float)
    steps = np.arange(1, len(loss) + 1) / max(int(views_per_step), 1)
    sv = np.asarray(history.get("s_v", [1.0] * len(loss)), dtype=float)[: len(loss)]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.4))

    def smooth(x, k=25):
        if len(x) == 0:
            return x
        k = max(1, min(k, len(x)))
        c = np.cumsum(np.insert(x, 0, 0.0))
        out = np.empty(len(x))
        for i in range(len(x)):
            lo = max(0, i - k + 1)
            out[i] = (c[i + 1] - c[lo]) / (i + 1 - lo)
        return out

    ax = axes[0]
    ax.plot(steps, loss, color="0.75", lw=0.6, label="per step")
    ax.plot(steps, smooth(loss), color="C0", label="running mean (25)")
    ax.set_ylabel("loss")
    ax.legend(fontsize=7)
    near = sv <= 1.0 + 0.1 * max(max_sv - 1.0, 0.0)
    sc = None
    for ax, key, lab in ((axes[1], "psnr", "training-view PSNR (dB)"), (axes[2], "eta", "rendered fraction")):
        y = np.asarray(history.get(key, []), dtype=float)[: len(loss)]
        if len(y) == 0:
            ax.set_ylabel(lab)
            continue
        sc = ax.scatter(steps[: len(y)], y, c=sv[: len(y)], s=3, cmap="viridis", vmin=1.0, vmax=max(max_sv, 1.0001))
        if near[: len(y)].any():
            yn = y[near[: len(y)]]
            ax.plot(steps[: len(y)][near[: len(y)]], smooth(yn, 10), color="C3",
                    label=f"s_v <= {1.0 + 0.1 * max(max_sv - 1.0, 0.0):.2f}, running mean")
            ax.legend(fontsize=7)
        ax.set_ylabel(lab)
    for ax in axes:
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    if sc is not None:
        fig.colorbar(sc, ax=axes[2], label="s_v of the step")
    fig.tight_layout()
    atomic_save(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100))
    plt.close(fig)
