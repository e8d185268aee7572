// Per-Gaussian rasterisation cost in one pass: the "ellipse_px" unit of
// clod_adapter.lod.cost.splat_cost (the alpha >= 1/255 ellipse's area in pixels, times the share of
// its box inside the image; 0 for a Gaussian the projection culls), from the means, quaternions,
// activated scales and opacities, with gsplat 1.5.3's projection (clod_adapter.render.projection:
// depth culling, the Jacobian at x/z, y/z clamped to 1.3x the field of view, eps2d, the
// opacity-aware extent, radius and box culling).
//
// Twin: clod_adapter.lod.cost.splat_cost at level 0 (clod_adapter.lod.cost.Footprints); the
// merge tree's cost and time budgets cost every node with it (clod_adapter.lod.cut.tree_node_costs),
// the calibrated schedule each training view's level (clod_adapter.train.loop.weighted_count).
// tests/test_cost.py holds the two together. Arithmetic in double (the twin projects in the
// model's dtype, so a radius on an integer boundary may round to the other side).
//
// ordered_prefix_count: the longest prefix of an order (scores descending, ties by position, NaN
// last) whose weights fit a budget, by a weighted selection (nth_element halving the range, then
// a sort of the last few): O(m) where the twin, clod_adapter.lod.cost.ordered_prefix_count's
// torch form, sorts all m. The sums are taken in another order, so the two agree up to rounding.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <vector>

namespace clod_ewa {  // projection.cpp
extern const double kAlphaThreshold, kExtend, kMaxRadius;
void camera(const double* R, const double* t, double fx, double cx, double fy, double cy, double width,
            double height, double* cam);
template <typename S>
void terms(const double* cam, const S* m, const S* q, const S* s, double* out);
bool footprint(double aa, double ab, double bb, double axb2, double px, double py, bool has_op, double op,
               double eps2d, double radius_clip, double width, double height, double* out);
}  // namespace clod_ewa

namespace {

constexpr int64_t kGrain = 8192;  // ~30 ns an element
using clod_ewa::kAlphaThreshold;
using clod_ewa::kExtend;
using clod_ewa::kMaxRadius;
constexpr double kPi = 3.14159265358979323846;

template <typename S>
void splat_cost_impl(int64_t n, const S* __restrict__ means, const S* __restrict__ quats,
                     const S* __restrict__ scales, const S* __restrict__ opac, const double* R_, const double* t_,
                     double fx, double cx, double fy, double cy, double width, double height, double near_plane,
                     double far_plane, double eps2d, double* __restrict__ out) {
    const double R[9] = {R_[0], R_[1], R_[2], R_[3], R_[4], R_[5], R_[6], R_[7], R_[8]};
    const double t[3] = {t_[0], t_[1], t_[2]};
    double cam[20];
    clod_ewa::camera(R, t, fx, cx, fy, cy, width, height, cam);
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
        for (int64_t i = begin; i < end; ++i) {
            out[i] = 0.0;
            const double mx = means[3 * i], my = means[3 * i + 1], mz = means[3 * i + 2];
            const double tz = R[6] * mx + R[7] * my + R[8] * mz + t[2];
            if (!(tz >= near_plane && tz <= far_plane)) continue;
            double o[7];
            clod_ewa::terms<S>(cam, means + 3 * i, quats + 4 * i, scales + 3 * i, o);
            const double px = o[1], py = o[2], aa = o[3], ab = o[4], bb = o[5], axb2 = o[6];
            const double op = static_cast<double>(opac[i]);
            double f[6];  // c00, c01, c11, det, radii
            if (!clod_ewa::footprint(aa, ab, bb, axb2, px, py, true, op, eps2d, 0.0, width, height, f)) continue;
            const double c00 = f[0], c01 = f[1], c11 = f[2], det = f[3], rad_x = f[4], rad_y = f[5];
            const double e2 = std::min(std::max(2.0 * std::log(std::max(op, kAlphaThreshold) / kAlphaThreshold), 0.0),
                                       kExtend * kExtend);
            const double rx = static_cast<double>(static_cast<int32_t>(std::min(rad_x, kMaxRadius)));
            const double ry = static_cast<double>(static_cast<int32_t>(std::min(rad_y, kMaxRadius)));
            const double bw = std::max(std::min(std::max(px + rx, 0.0), width) - std::min(std::max(px - rx, 0.0), width), 0.0);
            const double bh = std::max(std::min(std::max(py + ry, 0.0), height) - std::min(std::max(py - ry, 0.0), height), 0.0);
            const double inv_det = 1.0 / det;
            const double ca = c11 * inv_det, cb = -c01 * inv_det, cc = c00 * inv_det;
            const double sqrt_det_conic = std::sqrt(std::max(ca * cc - cb * cb, 1e-30));
            const double ell = kPi * e2 / sqrt_det_conic;
            const double full = std::max(4.0 * rx * ry, 1.0);
            out[i] = std::min(ell, full) * (bw * bh / full);
        }
    });
}

}  // namespace

// means [N, 3], quats [N, 4] (wxyz), scales [N, 3] (activated), opacities [N]: contiguous CPU, one
// float dtype; R [9] row-major and t [3] of the world-to-camera matrix; intrinsics and image size in
// pixels. Returns [N] float64 "ellipse_px" costs.
torch::Tensor splat_cost_cpu(torch::Tensor means, torch::Tensor quats, torch::Tensor scales, torch::Tensor opacities,
                             std::vector<double> R, std::vector<double> t, double fx, double cx, double fy, double cy,
                             int64_t width, int64_t height, double near_plane, double far_plane, double eps2d) {
    const int64_t n = means.size(0);
    TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && quats.dim() == 2 && quats.size(0) == n && quats.size(1) == 4 &&
                scales.dim() == 2 && scales.size(0) == n && scales.size(1) == 3 && opacities.dim() == 1 &&
                opacities.size(0) == n, "means [N, 3], quats [N, 4], scales [N, 3], opacities [N]");
    for (const auto& x : {means, quats, scales, opacities}) {
        TORCH_CHECK(x.is_contiguous() && x.device().is_cpu() && x.scalar_type() == means.scalar_type(),
                    "contiguous CPU tensors of one dtype");
    }
    TORCH_CHECK(R.size() == 9 && t.size() == 3, "R [9], t [3]");
    auto out = torch::empty({n}, means.options().dtype(torch::kFloat64));
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splat_cost", [&] {
        splat_cost_impl<scalar_t>(n, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
                                  opacities.data_ptr<scalar_t>(), R.data(), t.data(), fx, cx, fy, cy,
                                  static_cast<double>(width), static_cast<double>(height), near_plane, far_plane, eps2d,
                                  out.data_ptr<double>());
    });
    return out;
}

// scores [m] and weights [m] (>= 0): contiguous CPU float64. Returns the largest k such that the
// first k of the order (scores descending, ties by lower position, NaN last) weigh at most budget
// (0 for a negative budget).
int64_t ordered_prefix_count_cpu(torch::Tensor scores, torch::Tensor weights, double budget) {
    TORCH_CHECK(scores.dim() == 1 && weights.dim() == 1 && scores.size(0) == weights.size(0), "scores [m], weights [m]");
    for (const auto& x : {scores, weights}) {
        TORCH_CHECK(x.is_contiguous() && x.device().is_cpu() && x.scalar_type() == torch::kFloat64,
                    "contiguous CPU float64 tensors");
    }
    const int64_t m = scores.size(0);
    if (m == 0 || !(budget >= 0.0)) return 0;
    const double* s = scores.data_ptr<double>();
    const double* w = weights.data_ptr<double>();
    std::vector<int64_t> idx(m);
    std::iota(idx.begin(), idx.end(), int64_t{0});
    const auto first = [s](int64_t a, int64_t b) {  // a strict weak order: descending, NaN last, ties by position
        const bool na = std::isnan(s[a]), nb = std::isnan(s[b]);
        if (na || nb) return na != nb ? nb : a < b;
        return s[a] > s[b] || (s[a] == s[b] && a < b);
    };
    int64_t lo = 0, hi = m;  // idx[0, lo) is the order's first lo, weighing acc <= budget; the answer is in [lo, hi]
    double acc = 0.0;
    while (hi - lo > 64) {
        const int64_t mid = lo + (hi - lo) / 2;
        std::nth_element(idx.begin() + lo, idx.begin() + mid, idx.begin() + hi, first);
        double sum = 0.0;
        for (int64_t i = lo; i < mid; ++i) sum += w[idx[i]];
        if (acc + sum <= budget) {
            acc += sum;
            lo = mid;
        } else {
            hi = mid;
        }
    }
    std::sort(idx.begin() + lo, idx.begin() + hi, first);
    for (int64_t i = lo; i < hi; ++i) {
        acc += w[idx[i]];
        if (!(acc <= budget)) return i;
    }
    return hi;
}
