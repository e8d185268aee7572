"""The per-frame LoD terms: the C++ kernel against its torch twin, and the twin against the
[N, 3] arithmetic it replaced.

Every ``s_v`` frame tests all N centres against the frustum, takes their distances to the
camera and evaluates Eq. 2's mask before it knows what it draws: O(N) work that a coarse level
pays in full. Three forms, interleaved in one run, random centres in front of a 960x540 camera,
2 threads, ``OMP_WAIT_POLICY=PASSIVE`` (the CLIs' default):

* ``kernel``: :func:`clod_adapter.lod.rule.frame_terms` + :func:`clod_adapter.lod.rule.lod_mask` on the
  C++ kernel (``csrc/lod_terms.cpp``: one pass each, in double);
* ``rows``: the same calls on their torch twin (:func:`clod_adapter.lod.rule.in_frustum`,
  :func:`clod_adapter.lod.rule.normalized_distances`, the torch ``lod_mask``) on the centres' cached
  [3, N] rows, about 35 elementwise operations, each of which wakes OpenMP's second thread above
  32,768 elements (about 0.1 ms per operation under ``PASSIVE``);
* ``[N, 3]``: the frustum and distances as a [N, 3] x [3, 3] product and a division per
  coordinate (what the rows replaced), plus the torch mask;
* ``keep``: given the frame's terms, what an ``s_v`` frame needs of the mask: the kept indices
  and the frustum counts (``eta``, the level) from :func:`clod_adapter.lod.rule.lod_keep` in one call,
  against ``mask_ids``: the kernel's mask, then ``nonzero`` and two sums over [N] (what
  ``LodView.select`` did before), each a pass that wakes the second thread.

Goals (exit 1 when one is missed): the kernel at least 3x faster than its twin at 60,000
centres (the size of the scenes here, where the wake-ups dominate) and at least 1.5x at
1,000,000; the rows at least 2x faster than [N, 3] at 1,000,000; ``keep`` at least 1.3x faster
than ``mask_ids`` at 60,000 and at 1,000,000::

    python -m benchmarks.studies.frame_terms                 # 60,000 and 1,000,000 centres
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402


from clod_adapter.lod import rule as lod  # noqa: E402
from clod_adapter.render import native  # noqa: E402

#: (form, against, centres) -> the least speed-up (module docstring)
GOALS = {("kernel", "rows", 60_000): 3.0, ("kernel", "rows", 1_000_000): 1.5, ("rows", "n3", 1_000_000): 2.0,
         ("keep", "mask_ids", 60_000): 1.3, ("keep", "mask_ids", 1_000_000): 1.3}
S_V, TAU, EPS = 5.0, 0.005, 1e-8


def kernel_form(means, vm, K, w, h, op, sd):
    with native.use_impl("cpp"):
        fr, d = lod.frame_terms(means, vm, K, w, h)
        return fr, d, lod.lod_mask(op, d, sd, S_V, TAU, EPS)


def rows_form(means, vm, K, w, h, op, sd):
    with native.use_impl("torch"):
        fr = lod.in_frustum(means, vm, K, w, h)
        d = lod.normalized_distances(means, lod.camera_center(vm), fr)
        return fr, d, lod.lod_mask(op, d, sd, S_V, TAU, EPS)


def keep_form(fr, d, op, sd):
    with native.use_impl("cpp"):
        return lod.lod_keep(op, d, sd, S_V, fr, TAU, EPS)


def mask_ids_form(fr, d, op, sd):
    with native.use_impl("cpp"):
        m = lod.lod_mask(op, d, sd, S_V, TAU, EPS)
        return torch.nonzero(m).squeeze(1), int(fr.sum()), int((m & fr).sum())


def n3_form(means, vm, K, w, h, op, sd):
    pc = means @ vm[:3, :3].T + vm[:3, 3]
    z = pc[:, 2]
    front = z > 0.01
    zs = torch.where(front, z, torch.ones_like(z))
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    fr = front & (u >= 0) & (u < w) & (v >= 0) & (v < h) & torch.isfinite(u) & torch.isfinite(v)
    d = ((means - lod.camera_center(vm)).square() @ torch.ones(3)).sqrt()
    d = d / torch.where(fr, d, torch.zeros(())).max().clamp_min(1e-12)
    with native.use_impl("torch"):
        return fr, d, lod.lod_mask(op, d, sd, S_V, TAU, EPS)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[60_000, 1_000_000])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    vm = torch.eye(4)
    vm[2, 3] = 4.0
    K = torch.tensor([[800.0, 0, 480], [0, 800.0, 270], [0, 0, 1]])
    if not native.available():
        print(f"frame_terms: the C++ kernels do not build here ({native.error()!r})")
        return 1
    forms = {"kernel": kernel_form, "rows": rows_form, "n3": n3_form}
    ok = True
    with torch.no_grad():
        for n in a.sizes:
            gen = torch.Generator().manual_seed(0)
            means = torch.randn(n, 3, generator=gen)
            op, sd = torch.rand(n, generator=gen), torch.rand(n, generator=gen)
            args = (means, vm, K, 960, 540, op, sd)
            out = {name: f(*args) for name, f in forms.items()}
            terms = (out["kernel"][0], out["kernel"][1], op, sd)
            forms_n = {**forms, "keep": lambda *_: keep_form(*terms), "mask_ids": lambda *_: mask_ids_form(*terms)}
            out.update({name: forms_n[name]() for name in ("keep", "mask_ids")})
            ka, kb = out["keep"], out["mask_ids"]
            assert torch.equal(ka[0], kb[0]) and ka[1:] == kb[1:]
            for name in ("rows", "n3"):  # the same terms (the kernel's double arithmetic: to rounding)
                assert torch.equal(out["kernel"][0], out[name][0])
                assert torch.allclose(out["kernel"][1], out[name][1], rtol=1e-5, atol=1e-6)
                assert (out["kernel"][2] != out[name][2]).float().mean() < 1e-4
            times = {name: [] for name in forms_n}
            for _ in range(a.repeats):  # interleaved rounds
                for name, f in forms_n.items():
                    t0 = time.perf_counter()
                    f(*args)
                    times[name].append((time.perf_counter() - t0) * 1e3)
            med = {name: statistics.median(t) for name, t in times.items()}
            parts = []
            for (fa, fb, size), goal in GOALS.items():
                if size != n:
                    continue
                r = med[fb] / med[fa]
                ok &= r >= goal
                parts.append(f"{fa} vs {fb} {r:.1f}x ({'ok' if r >= goal else 'MISS'}, goal {goal:g}x)")
            print(f"{n:>9,} centres, ms per frame: kernel {med['kernel']:.2f}, rows {med['rows']:.2f}, "
                  f"[N, 3] {med['n3']:.2f}; then the kept ids and counts: kernel {med['keep']:.2f}, mask + "
                  f"nonzero + sums {med['mask_ids']:.2f}; " + ("; ".join(parts) or "printed only"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
