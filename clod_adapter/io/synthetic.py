"""The embedded default scene: a small synthetic forward-facing scene built with our own code.

A ground-truth Gaussian model (a textured back wall, a floor and a few foreground objects with
Gaussians of many sizes) is rendered by our rasteriser from a grid of forward-facing cameras and
written as a COLMAP scene folder; a perturbed copy of the ground truth (colours, opacities,
positions and sizes jittered) stands in for the user's "pretrained" checkpoint, so the demo has
real reconstruction error to lose or keep at each level of detail.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..gaussians import SH_C0, Gaussians
from .ply import write_ply
from .scene import Camera
from .colmap import write_colmap_scene
from ..render import rasterization

DEMO_WIDTH, DEMO_HEIGHT = 160, 120


def look_at(center: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """[4, 4] world-to-camera (OpenCV: x right, y down, z forward) looking from center at target."""
    f = target - center
    f = f / f.norm()
    down = torch.tensor([0.0, 1.0, 0.0], dtype=f.dtype)  # world y points down, as OpenCV
    r = torch.linalg.cross(down, f)
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    R = torch.stack([r, d, f])  # rows: camera axes in world
    vm = torch.eye(4, dtype=f.dtype)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ center
    return vm


def make_ground_truth(n: int = 6000, seed: int = 0) -> Gaussians:
    """A ground-truth model with ``n`` Gaussians, SH degree 1, in a box z in [2, 9]."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    parts = []
    # back wall at z ~ 9: a colour gradient with stripes, medium Gaussians
    nw = n // 3
    xy = (rnd(nw, 2) - 0.5) * torch.tensor([9.0, 7.0])
    wall = torch.cat([xy, 9.0 + 0.2 * rnd(nw, 1)], 1)
    wall_col = torch.stack([0.5 + 0.4 * torch.sin(xy[:, 0] * 1.3), 0.4 + 0.3 * torch.cos(xy[:, 1] * 2.1),
                            0.5 + 0.4 * torch.sign(torch.sin(xy[:, 0] * 4.0)) * 0.5], 1)
    parts.append((wall, wall_col, -2.3 + 0.4 * rnd(nw, 1)))
    # floor (y = +2 in OpenCV axes, i.e. below), checker texture
    nf = n // 6
    xz = torch.stack([(rnd(nf) - 0.5) * 9.0, 2.0 + 7.0 * rnd(nf)], 1)
    floor = torch.stack([xz[:, 0], torch.full((nf,), 2.0), xz[:, 1]], 1)
    chk = ((torch.floor(xz[:, 0] * 1.5) + torch.floor(xz[:, 1] * 1.5)) % 2)[:, None]
    parts.append((floor, 0.2 + 0.6 * chk * torch.tensor([[0.9, 0.8, 0.6]]), -2.6 + 0.4 * rnd(nf, 1)))
    # foreground objects: three spheres of small Gaussians with fine colour detail
    rest = n - nw - nf
    centers = torch.tensor([[-1.5, 0.5, 4.0], [1.2, -0.3, 5.5], [0.0, 1.0, 3.0]])
    radii = torch.tensor([0.9, 1.2, 0.6])
    k = torch.randint(0, 3, (rest,), generator=g)
    dirs = torch.randn(rest, 3, generator=g)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    obj = centers[k] + dirs * radii[k, None] * (0.85 + 0.15 * rnd(rest, 1))
    obj_col = 0.5 + 0.45 * torch.sin(dirs * 5.0 + k[:, None].float() * 2.0)
    parts.append((obj, obj_col, -3.9 + 0.6 * rnd(rest, 1)))
    means = torch.cat([p[0] for p in parts]).float()
    rgb = torch.cat([p[1] for p in parts]).clamp(0.02, 0.98).float()
    log_scales = torch.cat([p[2] for p in parts]).float().expand(-1, 3).clone()
    log_scales += 0.3 * torch.randn(len(means), 3, generator=g)
    quats = torch.randn(len(means), 4, generator=g)
    opacity_logits = 1.5 + 1.5 * torch.randn(len(means), generator=g)
    sh0 = ((rgb - 0.5) / SH_C0)[:, None, :]
    shN = 0.05 * torch.randn(len(means), 3, 3, generator=g)
    return Gaussians(means=means, quats=quats, log_scales=log_scales,
                     opacity_logits=opacity_logits, sh0=sh0, shN=shN)


def make_cameras(rows: int = 3, cols: int = 5, width: int = DEMO_WIDTH,
                 height: int = DEMO_HEIGHT) -> list[Camera]:
    """A forward-facing grid of cameras around the origin looking at (0, 0.3, 6), like LLFF."""
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    cams = []
    target = torch.tensor([0.0, 0.3, 6.0], dtype=torch.float64)
    for i in range(rows):
        for j in range(cols):
            c = torch.tensor([(j - (cols - 1) / 2) * 0.35, (i - (rows - 1) / 2) * 0.3, 0.0],
                             dtype=torch.float64)
            vm = look_at(c, target).float()
            name = f"view{i * cols + j:03d}.png"
            cams.append(Camera(name=name, image_path=Path(name), viewmat=vm, K=K.clone(),
                               width=width, height=height))
    return cams


def perturb(gt: Gaussians, seed: int = 1, strength: float = 1.0) -> Gaussians:
    """A "pretrained" stand-in: ``gt`` with jittered positions, sizes, opacities and colours."""
    g = torch.Generator().manual_seed(seed)
    n = len(gt)
    rn = lambda *s: torch.randn(*s, generator=g) * strength  # noqa: E731
    return Gaussians(
        means=gt.means + 0.15 * gt.scales * rn(n, 3),
        quats=gt.quats + 0.05 * rn(n, 4),
        log_scales=gt.log_scales + 0.05 * rn(n, 3),
        opacity_logits=gt.opacity_logits + 0.15 * rn(n),
        sh0=gt.sh0 + 0.05 * rn(n, 1, 3),
        shN=gt.shN + 0.02 * rn(*gt.shN.shape),
    )


@torch.no_grad()
def build_demo_scene(root: Path, n: int = 6000, seed: int = 0) -> tuple[Path, Path]:
    """Write the demo scene under ``root``.

    Returns:
        (scene folder with ``images/`` and ``sparse/0``, path of the "pretrained" .ply).
    """
    root = Path(root)
    gt = make_ground_truth(n, seed)
    cams = make_cameras()
    images = []
    for cam in cams:
        colors, _, _ = rasterization(gt.means, gt.quats, gt.scales, gt.opacities, gt.colors,
                                     cam.viewmat[None], cam.K[None], cam.width, cam.height,
                                     sh_degree=gt.sh_degree, backend="cpu")
        images.append((colors[0].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
    scene = root / "scene"
    write_colmap_scene(scene, cams, images)
    ply = root / "pretrained" / "point_cloud.ply"
    ply.parent.mkdir(parents=True, exist_ok=True)
    write_ply(ply, perturb(gt, seed + 1))
    return scene, ply
