// Per-frame LoD terms of CLoD-GS (Cheng et al., ICLR 2026, Sec. 3 and Eq. 2) in one pass each.
//
// Twins: clod_adapter.lod.rule.in_frustum + normalized_distances (frustum_distances) and
// clod_adapter.lod.rule.lod_mask (lod_mask), lod_keep (lod_keep) and window_opacities
// (lod_window_opacities); clod_adapter.lod.budget.critical_s_v (lod_critical); tests/test_lod_terms.py
// holds them together.
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
#include <tuple>
#include <vector>

namespace {

constexpr int64_t kGrain = 65536;     // ~3 ns an element: one thread below this
constexpr int64_t kGrainLog = 16384;  // the mask's log is ~15 ns an element
constexpr int64_t kGrainNewton = 4096;  // the critical s_v: a few exp an element
constexpr int kNewtonSteps = 80;        // budget._NEWTON_STEPS
constexpr double kEpsFloor = 1e-20;  // lod.EPS_FLOOR

template <typename S>
void frustum_distances_impl(int64_t n, const S* __restrict__ x, const S* __restrict__ y, const S* __restrict__ z,
                            const double* R_, const double* t_, double fx, double cx, double fy, double cy,
                            double width, double height, double near_plane, double c0, double c1, double c2,
                            bool* __restrict__ frustum, S* __restrict__ d_out) {
    const double R[9] = {R_[0], R_[1], R_[2], R_[3], R_[4], R_[5], R_[6], R_[7], R_[8]};  // locals: no aliasing
    const double t[3] = {t_[0], t_[1], t_[2]};
    const int64_t chunks = std::max<int64_t>(1, (n + kGrain - 1) / kGrain);
    std::vector<double> fr_max(chunks, 0.0);
    std::vector<char> any(chunks, 0);
    at::parallel_for(0, chunks, 1, [&](int64_t c_begin, int64_t c_end) {
        for (int64_t c = c_begin; c < c_end; ++c) {
            const int64_t b0 = c * kGrain, e = std::min(n, (c + 1) * kGrain);
            for (int64_t i = b0; i < e; ++i) {  // no reduction here: the compiler vectorises it
                const double px = x[i], py = y[i], pz = z[i];
                const double cz = R[6] * px + R[7] * py + R[8] * pz + t[2];
                const double cxs = R[0] * px + R[1] * py + R[2] * pz + t[0];
                const double cys = R[3] * px + R[4] * py + R[5] * pz + t[1];
                const double a = fx * cxs + cx * cz, b = fy * cys + cy * cz;  // pixel * z
                frustum[i] = (cz > near_plane) & (a >= 0.0) & (a < cz * width) & (b >= 0.0) & (b < cz * height);
                const double dx = px - c0, dy = py - c1, dz = pz - c2;
                d_out[i] = static_cast<S>(std::sqrt(dx * dx + dy * dy + dz * dz));  // the twin's max is of these
            }
            double fm = 0.0;
            char an = 0;
            for (int64_t i = b0; i < e; ++i) {
                const double v = frustum[i] ? static_cast<double>(d_out[i]) : 0.0;  // in the frustum: finite
                an |= static_cast<char>(frustum[i]);
                fm = v > fm ? v : fm;
            }
            fr_max[c] = fm; any[c] = an;
        }
    });
    bool has_frustum = false, has_nan = false;
    double fm = 0.0, am = -std::numeric_limits<double>::infinity();
    for (int64_t c = 0; c < chunks; ++c) {
        has_frustum |= any[c] != 0;
        fm = std::max(fm, fr_max[c]);
    }
    if (!has_frustum) {  // no centre in the frustum (rare): the maximum over all, NaN noticed
        for (int64_t i = 0; i < n; ++i) {
            const double dd = static_cast<double>(d_out[i]);
            has_nan |= dd != dd;
            am = std::max(am, dd);  // NaN never wins here (std::max keeps the first)
        }
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


// ids of lod_mask_impl's mask (ascending) and two counts over the frustum, without a [N] mask in
// torch: the mask, then per chunk the counts, then each chunk writes its ids at its offset (all in
// parallel chunks of kGrain; the twin's nonzero and two sums are each a pass over [N] that wakes
// OpenMP's second thread).
template <typename S>
void lod_keep_impl(int64_t n, const S* opac, const S* d_norm, const S* sigma_d, const bool* frustum, double s_v,
                   double tau, double eps, bool with_ids, const torch::TensorOptions& opts, torch::Tensor& ids,
                   int64_t& n_frustum, int64_t& n_kept_frustum) {
    std::vector<char> keep(static_cast<size_t>(n));
    bool* mask = reinterpret_cast<bool*>(keep.data());
    lod_mask_impl<S>(n, opac, d_norm, sigma_d, s_v, tau, eps, mask);
    const int64_t chunks = std::max<int64_t>(1, (n + kGrain - 1) / kGrain);
    std::vector<int64_t> nf(chunks, 0), nk(chunks, 0), nm(chunks, 0);
    at::parallel_for(0, chunks, 1, [&](int64_t c_begin, int64_t c_end) {
        for (int64_t c = c_begin; c < c_end; ++c) {
            int64_t f = 0, k = 0, m = 0;
            const int64_t e = std::min(n, (c + 1) * kGrain);
            for (int64_t i = c * kGrain; i < e; ++i) {
                const int64_t fi = frustum[i] ? 1 : 0, mi = mask[i] ? 1 : 0;
                f += fi; k += fi & mi; m += mi;
            }
            nf[c] = f; nk[c] = k; nm[c] = m;
        }
    });
    std::vector<int64_t> offset(chunks + 1, 0);
    n_frustum = 0; n_kept_frustum = 0;
    for (int64_t c = 0; c < chunks; ++c) {
        n_frustum += nf[c]; n_kept_frustum += nk[c];
        offset[c + 1] = offset[c] + nm[c];
    }
    ids = torch::empty({with_ids ? offset[chunks] : 0}, opts.dtype(torch::kLong));
    if (!with_ids) return;
    int64_t* out = ids.data_ptr<int64_t>();
    at::parallel_for(0, chunks, 1, [&](int64_t c_begin, int64_t c_end) {
        for (int64_t c = c_begin; c < c_end; ++c) {
            int64_t j = offset[c];
            const int64_t e = std::min(n, (c + 1) * kGrain);
            for (int64_t i = c * kGrain; i < e; ++i)
                if (mask[i]) out[j++] = i;
        }
    });
}


// The window fade's drawn opacities of the kept rows ids [k]: sigmoid(logit + level g) *
// clamp(m / width, 0, 1), m = log alpha + log-attenuation - log(tau s_v) (width <= 0: m > 0),
// one pass over k (the twin is about ten elementwise operations over [k], each waking OpenMP's
// second thread). alpha = 0 gives m = -inf: 0.
template <typename S>
void window_opacities_impl(int64_t k, const int64_t* ids, const S* opac, const S* logits, const S* gain,
                           const S* d_norm, const S* sigma_d, double s_v, double level, double tau, double eps,
                           double width, S* out) {
    const double log_ts = std::log(tau * s_v), e = std::max(eps, kEpsFloor);
    at::parallel_for(0, k, kGrainLog, [&](int64_t b, int64_t end) {
        for (int64_t j = b; j < end; ++j) {
            const int64_t i = ids[j];
            const double sd = std::max(static_cast<double>(sigma_d[i]), 0.0);
            const double x = static_cast<double>(d_norm[i]) * s_v;
            const double m = std::log(static_cast<double>(opac[i])) - x * x / (2.0 * sd * sd + e) - log_ts;
            const double w = width > 0.0 ? std::min(std::max(m / width, 0.0), 1.0) : (m > 0.0 ? 1.0 : 0.0);
            double l = static_cast<double>(logits[i]);
            if (gain != nullptr) l += level * static_cast<double>(gain[i]);
            out[j] = static_cast<S>(w / (1.0 + std::exp(-l)));
        }
    });
}

// The critical s_v of each Gaussian (budget.critical_s_v): the root of
// log alpha - log tau - a s^2 - log s = 0 for u = log s by Newton's method in double, started as the
// twin starts it; each Gaussian stops on its own once its step is below 1e-13 (the twin steps all
// of them until every step is), so the two agree to rounding.
template <typename S>
void critical_impl(int64_t n, const S* opac, const S* d_norm, const S* sigma_d, double tau, double eps,
                   double* out) {
    const double log_tau = std::log(tau), e = std::max(eps, kEpsFloor);
    at::parallel_for(0, n, kGrainNewton, [&](int64_t b, int64_t end) {
        for (int64_t i = b; i < end; ++i) {
            const double d = static_cast<double>(d_norm[i]);
            const double sd = std::max(static_cast<double>(sigma_d[i]), 0.0);  // NaN stays NaN
            const double a = d == 0.0 ? 0.0 : d * d / (2.0 * sd * sd + e);  // d' = 0: no attenuation
            const double A = std::log(static_cast<double>(opac[i])) - log_tau;
            if (!std::isfinite(A) || !std::isfinite(a)) {  // alpha = 0, a = inf, NaN: never drawn
                out[i] = 0.0;
                continue;
            }
            double u = std::min(A, 0.5 * (std::log(std::abs(A) + 1.0) - std::log(a)));  // log(0) = -inf: A
            for (int it = 0; it < kNewtonSteps; ++it) {
                const double ea = a * std::exp(2.0 * u);
                const double step = (A - ea - u) / (2.0 * ea + 1.0);
                u += step;
                if (std::abs(step) < 1e-13) break;
            }
            out[i] = std::exp(u);
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

// opacities, d_norm, sigma_d: [N] contiguous CPU, one float dtype; frustum [N] bool. Returns
// (ids [k] int64 ascending where alpha'' > tau s_v (empty unless with_ids), frustum.sum(),
// (mask & frustum).sum()).
std::tuple<torch::Tensor, int64_t, int64_t> lod_keep_cpu(torch::Tensor opacities, torch::Tensor d_norm,
                                                         torch::Tensor sigma_d, torch::Tensor frustum, double s_v,
                                                         double tau, double eps, bool with_ids) {
    TORCH_CHECK(opacities.is_contiguous() && d_norm.is_contiguous() && sigma_d.is_contiguous() &&
                frustum.is_contiguous(), "contiguous inputs");
    TORCH_CHECK(opacities.scalar_type() == d_norm.scalar_type() && sigma_d.scalar_type() == d_norm.scalar_type(),
                "one dtype");
    TORCH_CHECK(frustum.scalar_type() == torch::kBool, "frustum must be bool");
    const int64_t n = d_norm.numel();
    TORCH_CHECK(opacities.numel() == n && sigma_d.numel() == n && frustum.numel() == n, "[N] inputs");
    torch::Tensor ids;
    int64_t nf = 0, nk = 0;
    AT_DISPATCH_FLOATING_TYPES(d_norm.scalar_type(), "lod_keep_cpu", [&] {
        lod_keep_impl<scalar_t>(n, opacities.data_ptr<scalar_t>(), d_norm.data_ptr<scalar_t>(),
                                sigma_d.data_ptr<scalar_t>(), frustum.data_ptr<bool>(), s_v, tau, eps, with_ids,
                                d_norm.options(), ids, nf, nk);
    });
    return std::make_tuple(ids, nf, nk);
}

// ids [k] int64 (rows of the [N] inputs, in range); opacities (activated), opacity_logits, d_norm,
// sigma_d [N] contiguous CPU, one float dtype; gain [N] the opacity-logit gain or an empty tensor.
// Returns [k]: the window fade's drawn opacities (lod.window_opacities).
torch::Tensor lod_window_opacities_cpu(torch::Tensor ids, torch::Tensor opacities, torch::Tensor logits,
                                       torch::Tensor gain, torch::Tensor d_norm, torch::Tensor sigma_d,
                                       double s_v, double level, double tau, double eps, double width) {
    TORCH_CHECK(ids.scalar_type() == torch::kLong && ids.dim() == 1 && ids.is_contiguous(), "ids must be [k] int64");
    const int64_t n = d_norm.numel();
    const bool has_gain = gain.numel() > 0;
    for (const torch::Tensor* t : {&opacities, &logits, &d_norm, &sigma_d}) {
        TORCH_CHECK(t->is_contiguous() && t->numel() == n && t->scalar_type() == d_norm.scalar_type(),
                    "[N] contiguous inputs of one dtype");
    }
    TORCH_CHECK(!has_gain || (gain.is_contiguous() && gain.numel() == n && gain.scalar_type() == d_norm.scalar_type()),
                "gain must be [N] of the inputs' dtype or empty");
    const int64_t k = ids.numel();
    auto out = torch::empty({k}, d_norm.options());
    AT_DISPATCH_FLOATING_TYPES(d_norm.scalar_type(), "lod_window_opacities_cpu", [&] {
        window_opacities_impl<scalar_t>(k, ids.data_ptr<int64_t>(), opacities.data_ptr<scalar_t>(),
                                        logits.data_ptr<scalar_t>(), has_gain ? gain.data_ptr<scalar_t>() : nullptr,
                                        d_norm.data_ptr<scalar_t>(), sigma_d.data_ptr<scalar_t>(), s_v, level, tau,
                                        eps, width, out.data_ptr<scalar_t>());
    });
    return out;
}

// opacities (activated), d_norm, sigma_d (raw): [N] contiguous CPU, one float dtype. Returns [N]
// float64 critical s_v (budget.critical_s_v).
torch::Tensor lod_critical_cpu(torch::Tensor opacities, torch::Tensor d_norm, torch::Tensor sigma_d, double tau,
                               double eps) {
    TORCH_CHECK(opacities.is_contiguous() && d_norm.is_contiguous() && sigma_d.is_contiguous(), "contiguous inputs");
    TORCH_CHECK(opacities.scalar_type() == d_norm.scalar_type() && sigma_d.scalar_type() == d_norm.scalar_type(),
                "one dtype");
    const int64_t n = d_norm.numel();
    TORCH_CHECK(opacities.numel() == n && sigma_d.numel() == n, "[N] inputs");
    auto out = torch::empty({n}, d_norm.options().dtype(torch::kDouble));
    AT_DISPATCH_FLOATING_TYPES(d_norm.scalar_type(), "lod_critical_cpu", [&] {
        critical_impl<scalar_t>(n, opacities.data_ptr<scalar_t>(), d_norm.data_ptr<scalar_t>(),
                                sigma_d.data_ptr<scalar_t>(), tau, eps, out.data_ptr<double>());
    });
    return out;
}
