// Per-frame LoD terms of CLoD-GS (Cheng et al., ICLR 2026, Sec. 3 and Eq. 2) in one pass each.
//
// Twins: clod_adapter.lod.in_frustum + normalized_distances (frustum_distances) and
// clod_adapter.lod.lod_mask (lod_mask); tests/test_lod_terms.py holds them together.
// Every frame of a level of detail runs these over all N Gaussians before it knows what it draws.
// As ~30 elementwise torch operations at N = 60,000 each one pays OpenMP's wake-up of the
// second thread (about 0.1 ms under OMP_WAIT_POLICY=PASSIVE); here they are one or two parallel
// regions (at::parallel_for, grain 65536: one thread below that), arithmetic in double.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace {

constexpr int64_t kGrain = 65536;     // ~3 ns an element: one thread below this
constexpr int64_t kGrainLog = 16384;  // the mask's log is ~15 ns an element
constexpr double kEpsFloor = 1e-20;  // lod.EPS_FLOOR

template <typename S>
void frustum_distances_impl(int64_t n, const S* x, const S* y, const S* z, const double* R, const double* t,
                            double fx, double cx, double fy, double cy, double width, double height,
                            double near_plane, double c0, double c1, double c2, bool* frustum, S* d_out) {
    const int64_t chunks = std::max<int64_t>(1, (n + kGrain - 1) / kGrain);
    std::vector<double> fr_max(chunks, 0.0), all_max(chunks, -std::numeric_limits<double>::infinity());
    std::vector<char> any(chunks, 0), nan_all(chunks, 0);
    at::parallel_for(0, chunks, 1, [&](int64_t c_begin, int64_t c_end) {
        for (int64_t c = c_begin; c < c_end; ++c) {
            double fm = 0.0, am = -std::numeric_limits<double>::infinity();
            char an = 0, nn = 0;
            const int64_t e = std::min(n, (c + 1) * kGrain);
            for (int64_t i = c * kGrain; i < e; ++i) {  // branch-free: the compiler vectorises it
                const double px = x[i], py = y[i], pz = z[i];
                const double cz = R[6] * px + R[7] * py + R[8] * pz + t[2];
                const double cxs = R[0] * px + R[1] * py + R[2] * pz + t[0];
                const double cys = R[3] * px + R[4] * py + R[5] * pz + t[1];
                const double a = fx * cxs + cx * cz, b = fy * cys + cy * cz;  // pixel * z
                const bool ok = (cz > near_plane) & (a >= 0.0) & (a < cz * width) & (b >= 0.0) & (b < cz * height);
                frustum[i] = ok;
                const double dx = px - c0, dy = py - c1, dz = pz - c2;
                const S ds = static_cast<S>(std::sqrt(dx * dx + dy * dy + dz * dz));
                d_out[i] = ds;  // the twin takes its maximum of these stored values
                const double dd = static_cast<double>(ds);
                an |= static_cast<char>(ok);
                nn |= static_cast<char>(dd != dd);
                fm = std::max(fm, ok ? dd : 0.0);  // a centre in the frustum is finite
                am = std::max(am, dd);             // NaN never wins here (std::max keeps the first)
            }
            fr_max[c] = fm; all_max[c] = am; any[c] = an; nan_all[c] = nn;
        }
    });
    bool has_frustum = false, has_nan = false;
    double fm = 0.0, am = -std::numeric_limits<double>::infinity();
    for (int64_t c = 0; c < chunks; ++c) {
        has_frustum |= any[c] != 0; has_nan |= nan_all[c] != 0;
        fm = std::max(fm, fr_max[c]); am = std::max(am, all_max[c]);
    }
    // the twin: max over the frustum, else over all (NaN -> 1, inf -> the dtype's max), >= 1e-12
    double dmax = has_frustum ? fm : (has_nan ? std::numeric_limits<double>::quiet_NaN() : am);
    if (std::isnan(dmax)) dmax = 1.0;
    if (std::isinf(dmax)) dmax = static_cast<double>(std::numeric_limits<S>::max());
    const S dm = static_cast<S>(std::max(dmax, 1e-12));
    at::parallel_for(0, n, kGrain, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i) d_out[i] = d_out[i] / dm;
    });
}

template <typename S>
void lod_mask_impl(int64_t n, const S* opac, const S* d_norm, const S* sigma_d, double s_v, double tau, double eps,
                   bool* out) {
    const double log_ts = std::log(tau * s_v), e = std::max(eps, kEpsFloor);
    at::parallel_for(0, n, kGrainLog, [&](int64_t b, int64_t end) {
        for (int64_t i = b; i < end; ++i) {
            const double sd = std::max(static_cast<double>(sigma_d[i]), 0.0);
            const double x = static_cast<double>(d_norm[i]) * s_v;
            const double thr = x * x / (2.0 * sd * sd + e) + log_ts;
            // log(alpha) <= 0: a threshold >= 0 rejects without the log (most of a coarse level)
            out[i] = thr < 0.0 && std::log(static_cast<double>(opac[i])) > thr;  // log(0) = -inf, NaN: never drawn
        }
    });
}

}  // namespace

// cols [3, N] contiguous float/double (the centres' rows, lod.centre_columns); R [9] row-major and
// t [3] of the world-to-camera matrix; intrinsics and image size in pixels; camera centre (world).
// Returns {frustum [N] bool, d_norm [N] cols' dtype}.
std::vector<torch::Tensor> lod_frustum_distances(torch::Tensor cols, std::vector<double> R, std::vector<double> t,
                                                 double fx, double cx, double fy, double cy, int64_t width,
                                                 int64_t height, double near_plane, std::vector<double> center) {
    TORCH_CHECK(cols.dim() == 2 && cols.size(0) == 3 && cols.is_contiguous() && cols.device().is_cpu(),
                "cols must be a contiguous CPU [3, N] tensor");
    TORCH_CHECK(R.size() == 9 && t.size() == 3 && center.size() == 3, "R [9], t [3], center [3]");
    const int64_t n = cols.size(1);
    auto frustum = torch::empty({n}, cols.options().dtype(torch::kBool));
    auto d = torch::empty({n}, cols.options());
    AT_DISPATCH_FLOATING_TYPES(cols.scalar_type(), "lod_frustum_distances", [&] {
        const scalar_t* p = cols.data_ptr<scalar_t>();
        frustum_distances_impl<scalar_t>(n, p, p + n, p + 2 * n, R.data(), t.data(), fx, cx, fy, cy,
                                         static_cast<double>(width), static_cast<double>(height), near_plane,
                                         center[0], center[1], center[2], frustum.data_ptr<bool>(),
                                         d.data_ptr<scalar_t>());
    });
    return {frustum, d};
}

// opacities, d_norm, sigma_d: [N] contiguous CPU, one float dtype. Returns [N] bool: alpha'' > tau s_v.
torch::Tensor lod_mask_cpu(torch::Tensor opacities, torch::Tensor d_norm, torch::Tensor sigma_d, double s_v,
                           double tau, double eps) {
    TORCH_CHECK(opacities.is_contiguous() && d_norm.is_contiguous() && sigma_d.is_contiguous(), "contiguous inputs");
    TORCH_CHECK(opacities.scalar_type() == d_norm.scalar_type() && sigma_d.scalar_type() == d_norm.scalar_type(),
                "one dtype");
    const int64_t n = d_norm.numel();
    TORCH_CHECK(opacities.numel() == n && sigma_d.numel() == n, "[N] inputs");
    auto out = torch::empty({n}, d_norm.options().dtype(torch::kBool));
    AT_DISPATCH_FLOATING_TYPES(d_norm.scalar_type(), "lod_mask_cpu", [&] {
        lod_mask_impl<scalar_t>(n, opacities.data_ptr<scalar_t>(), d_norm.data_ptr<scalar_t>(),
                                sigma_d.data_ptr<scalar_t>(), s_v, tau, eps, out.data_ptr<bool>());
    });
    return out;
}
