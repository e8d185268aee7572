// CPU per-pixel compositor for 3D Gaussian Splatting (classic mode).
//
// Semantics follow gsplat 1.5.3 rasterize_to_pixels (RasterizeToPixels3DGS
// Fwd/Bwd .cu) for a single camera:
//   pixel centre (x + 0.5, y + 0.5); delta = mean - centre;
//   sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy;
//   alpha = min(0.999, opacity * exp(-sigma));
//   skip if sigma < 0 or alpha < 1/255;
//   next_T = T * (1 - alpha); if next_T <= 1e-4 the pixel is done and this
//   Gaussian is NOT added (exclusive rule); else accumulate and T = next_T.
// The backward walks each pixel back to front starting from its last
// contributing index, recovering T by division (T /= 1 - alpha).
//
// CPU organisation: OpenMP over tiles (dynamic schedule; the backward's
// deterministic mode, see below, uses a fixed tile -> buffer mapping). Within a tile we
// iterate Gaussian-major (front to back in the forward, back to front in the
// backward) and, for each Gaussian, only over the pixels inside the
// conservative bounding box of its alpha >= 1/255 ellipse. Per pixel the
// order of Gaussians is unchanged, so the result is identical to the
// per-pixel loop. Pixel state lives in small per-tile arrays. Per-Gaussian
// gradients are summed over a tile in registers and added into a per-thread
// buffer ([N, 6 + D] per thread), reduced at the end (no atomics), in thread
// order. With dynamic scheduling which tiles land in which buffer varies from
// run to run, so float sums differ in the last bits; deterministic=true gives
// buffer b the tiles b, b + nthreads, ... (static schedule, increasing order)
// and the backward is then bit-reproducible for a given nthreads. The forward
// is always deterministic (each pixel is written by one thread).
//
// SIMD: built by GCC for an x86-64 CPU with AVX2 and FMA, the float kernels composite four
// pixels of a row at once (composite_simd.cpp). Every lane does the scalar code's arithmetic
// in the scalar code's order (no contraction), its exp is glibc's expf algorithm (ARM optimized-routines, the FMA
// variant glibc selects on such CPUs) and the backward's sums over pixels are added lane by lane
// in pixel order, so the result is bit-identical to the scalar kernel, which stays the twin
// (composite_simd(0) selects it; tests hold the two equal). The vector path is used only after
// a self-check of its exp against this process's std::exp; double inputs stay scalar.
#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

namespace clod_simd {  // composite_simd.cpp
bool active();
int set_mode(int mode);
int forward_row(uint64_t* wrow, int xa, int xb, int px0, int pbase, float mx, float dy, float a, float b,
                float op, float sthr, float cdy2, const float* cg, int D, float* T, float* col, int cs,
                int32_t* last, int32_t idx);
bool backward_row(const uint64_t* row, int xa, int xb, int px0, int pbase, float mx, float dy, float a, float b,
                  float c, float op, float sthr, float cdy2, const float* cg, int D, double* T, const double* w,
                  const float* vc, double* buf, int cs, double* sums);
}  // namespace clod_simd

namespace {

template <typename S>
struct Consts;
template <>
struct Consts<float> {
    static constexpr float max_alpha = 0.999f;
    static constexpr float alpha_thr = 1.0f / 255.0f;
    static constexpr float trans_thr = 1e-4f;
};
template <>
struct Consts<double> {
    static constexpr double max_alpha = 0.999;
    static constexpr double alpha_thr = 1.0 / 255.0;
    static constexpr double trans_thr = 1e-4;
};

// Per-Gaussian packed parameters + conservative pixel bounding box.
template <typename S>
struct GParam {
    S mx, my, a, b, c, op;
    S sthr;          // sigma > sthr  =>  alpha < 1/255 for sure (skips exp)
    int32_t x0, x1;  // inclusive pixel range (image coordinates)
    int32_t y0, y1;
    // exact per-row span of the (margin-inflated) alpha >= 1/255 ellipse:
    // px in [mx + ba*dy - hw, mx + ba*dy + hw], hw = sqrt(two_a_sm - det*dy^2) * inv_a
    bool span_ok;
    double ba, inv_a, two_a_sm, det;
};

// Local (tile) x range [xa, xb] of row with centre offset dy (= my - py).
template <typename S>
inline bool row_span(const GParam<S>& q, double dy, int32_t px0, int32_t pw,
                     int32_t& xa, int32_t& xb) {
    if (!q.span_ok) {
        xa = std::max(q.x0 - px0, 0);
        xb = std::min(q.x1 - px0, pw - 1);
        return xa <= xb;
    }
    const double disc = q.two_a_sm - q.det * dy * dy;
    if (disc < 0) return false;
    const double hw = std::sqrt(disc) * q.inv_a + 1e-3;
    const double c = static_cast<double>(q.mx) + q.ba * dy - 0.5 - px0;
    // ceil/floor without libm calls (no SSE4.1 at baseline -O3); values are
    // clamped to the tile first so the int conversion cannot overflow
    double lo = c - hw, hi = c + hw;
    if (!(lo <= hi)) return false;  // NaN guard
    if (lo < -1.0) lo = -1.0;
    if (hi > pw) hi = pw;
    int32_t il = static_cast<int32_t>(lo);
    if (il < lo) ++il;  // ceil
    int32_t ih = static_cast<int32_t>(hi);
    if (ih > hi) --ih;  // floor
    xa = il < 0 ? 0 : il;
    xb = ih > pw - 1 ? pw - 1 : ih;
    return xa <= xb;
}

// The vector rows (composite_simd.cpp) take a Gaussian in float with a well-conditioned ellipse
// and a finite skip threshold (every drawn sigma in [0, 80]), rows of at most 64 pixels and at
// most 16 channels; `on` is clod_simd::active() read once per call.
template <typename S>
inline bool simd_rows(const GParam<S>& q, int nw, int D, bool on) {
    if constexpr (!std::is_same<S, float>::value) {
        return false;
    } else {
        return on && nw == 1 && D <= 16 && q.span_ok && q.sthr <= 80.0f;  // NaN sthr: false
    }
}

// Iterate the set bits of a row bitmask restricted to [xa, xb].
template <typename F>
inline void for_bits(const uint64_t* row, int32_t xa, int32_t xb, F&& f) {
    const int w0 = xa >> 6, w1 = xb >> 6;
    for (int w = w0; w <= w1; ++w) {
        const int lo = std::max(xa - (w << 6), 0);
        const int hi = std::min(xb - (w << 6), 63);
        uint64_t m = (hi == 63 ? ~0ULL : ((1ULL << (hi + 1)) - 1)) & ~((1ULL << lo) - 1);
        m &= row[w];
        while (m) {
            const int bit = __builtin_ctzll(m);
            m &= m - 1;
            f((w << 6) + bit);
        }
    }
}

inline int32_t clamp_to_int(double v, int32_t lo, int32_t hi) {
    if (!(v >= lo)) return lo;  // also NaN -> lo
    if (v > hi) return hi;
    return static_cast<int32_t>(v);
}

template <typename S>
void precompute_params(
    int64_t N,
    const S* means2d,
    const S* conics,
    const S* opac,
    int32_t W,
    int32_t H,
    int nthreads,
    std::vector<GParam<S>>& out) {
    out.resize(N);
    GParam<S>* P = out.data();
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t g = 0; g < N; ++g) {
        GParam<S> q;
        q.mx = means2d[2 * g];
        q.my = means2d[2 * g + 1];
        q.a = conics[3 * g];
        q.b = conics[3 * g + 1];
        q.c = conics[3 * g + 2];
        q.op = opac[g];
        // full image by default (always correct, just slower)
        q.x0 = 0;
        q.x1 = W - 1;
        q.y0 = 0;
        q.y1 = H - 1;
        q.sthr = std::numeric_limits<S>::quiet_NaN();  // never skip early
        q.span_ok = false;
        q.ba = q.inv_a = q.two_a_sm = q.det = 0.0;
        const double op = q.op;
        if (op < static_cast<double>(Consts<S>::alpha_thr)) {
            // alpha <= opacity < 1/255 everywhere sigma >= 0: invisible.
            q.x0 = 0;
            q.x1 = -1;
            q.y0 = 0;
            q.y1 = -1;
        } else if (std::isfinite(op)) {
            const double s = std::log(255.0 * op);  // alpha >= 1/255 <=> sigma <= s
            const double sm = s + 1e-3 * (1.0 + std::fabs(s));
            q.sthr = static_cast<S>(sm);
            const double a = q.a, b = q.b, c = q.c;
            const double mx = q.mx, my = q.my;
            const double det = a * c - b * b;
            // well-conditioned only (|rho| < ~0.995): keeps float rounding of
            // sigma far below the 1e-3 relative margin in sm
            if (a > 0 && c > 0 && det > 1e-2 * a * c && std::isfinite(det) &&
                std::isfinite(mx) && std::isfinite(my)) {
                const double rx = std::sqrt(2.0 * sm * c / det);
                const double ry = std::sqrt(2.0 * sm * a / det);
                // pixel x is inside iff |mx - (x + 0.5)| <= rx; one pixel margin
                q.x0 = clamp_to_int(std::ceil(mx - rx - 0.5) - 1.0, 0, W);
                q.x1 = clamp_to_int(std::floor(mx + rx - 0.5) + 1.0, -1, W - 1);
                q.y0 = clamp_to_int(std::ceil(my - ry - 0.5) - 1.0, 0, H);
                q.y1 = clamp_to_int(std::floor(my + ry - 0.5) + 1.0, -1, H - 1);
                q.span_ok = true;
                q.ba = b / a;
                q.inv_a = 1.0 / a;
                q.two_a_sm = 2.0 * a * sm;
                q.det = det;
            }
        }
        P[g] = q;
    }
}

// how many Gaussians of a tile's list ahead their parameters (and gradient rows) are prefetched
constexpr int64_t kPrefetch = 8;

inline void tile_range(
    const int64_t* offsets, int64_t ntiles, int64_t M, int64_t t,
    int64_t& start, int64_t& end) {
    start = offsets[t];
    end = (t == ntiles - 1) ? M : offsets[t + 1];
    if (start < 0) start = 0;
    if (end > M) end = M;
}

// ----------------------------------------------------------------------------
// Forward
// ----------------------------------------------------------------------------
template <typename S, int CD>
void forward_impl(
    int64_t N, int Ddyn,
    const S* means2d, const S* conics, const S* colors, const S* opac,
    const S* bg, int32_t W, int32_t H, int32_t ts, int32_t th, int32_t tw,
    const int64_t* offsets, const int64_t* ids, int64_t M,
    S* out_col, S* out_alpha, S* out_T, int32_t* out_last, int nthreads) {
    const int D = CD > 0 ? CD : Ddyn;
    std::vector<GParam<S>> params;
    precompute_params<S>(N, means2d, conics, opac, W, H, nthreads, params);
    const GParam<S>* P = params.data();
    const int64_t ntiles = static_cast<int64_t>(th) * tw;
    constexpr S maxA = Consts<S>::max_alpha;
    constexpr S athr = Consts<S>::alpha_thr;
    constexpr S tthr = Consts<S>::trans_thr;
    const bool simd_on = clod_simd::active();

#pragma omp parallel num_threads(nthreads)
    {
        const int npix_max = ts * ts;
        const int cs = npix_max + 4;  // colour plane stride (SoA: col[k * cs + p]); 4 lanes of padding
        std::vector<S> Tv(cs), colv(static_cast<size_t>(cs) * D);
        std::vector<int32_t> lastv(cs);
        const int nw_max = (ts + 63) / 64;
        std::vector<uint64_t> actv(static_cast<size_t>(ts) * nw_max);
#pragma omp for schedule(dynamic, 1)
        for (int64_t t = 0; t < ntiles; ++t) {
            const int32_t ty = static_cast<int32_t>(t / tw);
            const int32_t tx = static_cast<int32_t>(t % tw);
            const int32_t px0 = tx * ts, py0 = ty * ts;
            const int32_t pw = std::min(ts, W - px0), ph = std::min(ts, H - py0);
            if (pw <= 0 || ph <= 0) continue;
            const int npix = pw * ph;
            const int nw = (pw + 63) / 64;
            S* T = Tv.data();
            S* col = colv.data();
            int32_t* last = lastv.data();
            uint64_t* act = actv.data();  // active (not done) pixels, per row
            std::fill(T, T + npix, S(1));
            for (int k = 0; k < D; ++k) std::fill_n(col + static_cast<size_t>(k) * cs, npix, S(0));
            std::fill(last, last + npix, -1);
            for (int ly = 0; ly < ph; ++ly) {
                for (int w = 0; w < nw; ++w) {
                    const int nb = std::min(64, pw - 64 * w);
                    act[ly * nw + w] = nb == 64 ? ~0ULL : ((1ULL << nb) - 1);
                }
            }
            int ndone = 0;
            int64_t start, end;
            tile_range(offsets, ntiles, M, t, start, end);
            for (int64_t idx = start; idx < end; ++idx) {
                const int64_t g = ids[idx];
                // the Gaussians are visited in depth order, at random in memory: fetch ahead
                if (idx + kPrefetch < end) __builtin_prefetch(P + ids[idx + kPrefetch]);
                const GParam<S>& q = P[g];
                const int32_t y0 = std::max(q.y0, py0), y1 = std::min(q.y1, py0 + ph - 1);
                if (y0 > y1 || q.x0 > px0 + pw - 1 || q.x1 < px0) continue;
                const S mx = q.mx, my = q.my, a = q.a, b = q.b, c = q.c, op = q.op;
                const S sthr = q.sthr;
                const S* cg = colors + g * D;
                const bool vec = simd_rows(q, nw, D, simd_on);
                for (int32_t y = y0; y <= y1; ++y) {
                    const int ly = y - py0;
                    const uint64_t* row = act + ly * nw;
                    if (nw == 1 && row[0] == 0) continue;
                    const S dy = my - (static_cast<S>(y) + S(0.5));
                    int32_t xa, xb;
                    if (!row_span(q, static_cast<double>(dy), px0, pw, xa, xb)) continue;
                    const S cdy2 = c * dy * dy;
                    uint64_t* wrow = act + ly * nw;
                    if constexpr (std::is_same<S, float>::value) {
                        if (vec) {
                            ndone += clod_simd::forward_row(wrow, xa, xb, px0, ly * pw, mx, dy, a, b, op, sthr, cdy2,
                                                            cg, D, T, col, cs, last, static_cast<int32_t>(idx));
                            continue;
                        }
                    }
                    for_bits(row, xa, xb, [&](int lx) {
                        const int p = ly * pw + lx;
                        const S dx = mx - (static_cast<S>(px0 + lx) + S(0.5));
                        const S sigma = S(0.5) * (a * dx * dx + cdy2) + b * dx * dy;
                        if (sigma > sthr) return;
                        const S alpha = std::min(maxA, op * std::exp(-sigma));
                        if (sigma < S(0) || alpha < athr) return;
                        const S Tp = T[p];
                        const S nT = Tp * (S(1) - alpha);
                        if (nT <= tthr) {
                            wrow[lx >> 6] &= ~(1ULL << (lx & 63));
                            ++ndone;
                            return;
                        }
                        const S vis = alpha * Tp;
                        for (int k = 0; k < D; ++k) col[static_cast<size_t>(k) * cs + p] += cg[k] * vis;
                        last[p] = static_cast<int32_t>(idx);
                        T[p] = nT;
                    });
                }
                if (ndone == npix) break;
            }
            // write out
            for (int ly = 0; ly < ph; ++ly) {
                for (int lx = 0; lx < pw; ++lx) {
                    const int p = ly * pw + lx;
                    const int64_t pix = static_cast<int64_t>(py0 + ly) * W + (px0 + lx);
                    const S Tp = T[p];
                    out_alpha[pix] = S(1) - Tp;
                    if (out_T != nullptr) {  // the backward's state, not kept for a frame without gradients
                        out_T[pix] = Tp;
                        out_last[pix] = last[p];
                    }
                    S* oc = out_col + pix * D;
                    const S* cp = col + p;
                    if (bg != nullptr) {
                        for (int k = 0; k < D; ++k) oc[k] = cp[static_cast<size_t>(k) * cs] + Tp * bg[k];
                    } else {
                        for (int k = 0; k < D; ++k) oc[k] = cp[static_cast<size_t>(k) * cs];
                    }
                }
            }
        }
    }
}

// ----------------------------------------------------------------------------
// Backward
// ----------------------------------------------------------------------------
template <typename S, int CD>
void backward_impl(
    int64_t N, int Ddyn,
    const S* means2d, const S* conics, const S* colors, const S* opac,
    const S* bg, int32_t W, int32_t H, int32_t ts, int32_t th, int32_t tw,
    const int64_t* offsets, const int64_t* ids, int64_t M,
    const S* Tfinal, const int32_t* lastids, const S* v_col, const S* v_alpha_img,
    S* g_means, S* g_conics, S* g_colors, S* g_opac, int nthreads, bool deterministic) {
    const int D = CD > 0 ? CD : Ddyn;
    const int G = 6 + D;  // packed gradient stride: mx my a b c op colors...
    std::vector<GParam<S>> params;
    precompute_params<S>(N, means2d, conics, opac, W, H, nthreads, params);
    const GParam<S>* P = params.data();
    const int64_t ntiles = static_cast<int64_t>(th) * tw;
    constexpr S maxA = Consts<S>::max_alpha;
    constexpr S athr = Consts<S>::alpha_thr;
    const bool simd_on = clod_simd::active();

    // per-thread gradient buffers
    std::vector<std::vector<S>> bufs(nthreads);

#pragma omp parallel num_threads(nthreads)
    {
        const int tid = omp_get_thread_num();
        // dynamic mode: one buffer per thread; deterministic mode: buffer b belongs to the
        // fixed tile set {b, b + nthreads, ...} whichever thread runs it (allocated there)
        if (!deterministic) bufs[tid].assign(static_cast<size_t>(N) * G, S(0));
        const int npix_max = ts * ts;
        const int cs = npix_max + 4;  // channel plane stride (SoA: buf[k * cs + p]); 4 lanes of padding
        std::vector<double> Tv(cs), bufv(static_cast<size_t>(cs) * D);
        std::vector<double> wv(cs);  // T_final * (v_alpha - bg . v_col)
        std::vector<S> vcv(static_cast<size_t>(cs) * D);
        std::vector<int32_t> lastv(npix_max);
        std::vector<double> sumv(6 + D);  // one Gaussian's sums over pixels: mx my a b c op colours...
        const int nw_max = (ts + 63) / 64;
        std::vector<uint64_t> actv(static_cast<size_t>(ts) * nw_max);
        std::vector<std::pair<int32_t, int32_t>> order(npix_max);
        // one tile's gradients, summed over the tile and added into gout ([N, G])
        auto tile_body = [&](int64_t t, S* gout) {
            const int32_t ty = static_cast<int32_t>(t / tw);
            const int32_t tx = static_cast<int32_t>(t % tw);
            const int32_t px0 = tx * ts, py0 = ty * ts;
            const int32_t pw = std::min(ts, W - px0), ph = std::min(ts, H - py0);
            if (pw <= 0 || ph <= 0) return;
            int64_t start, end;
            tile_range(offsets, ntiles, M, t, start, end);
            if (end <= start) return;
            const int npix = pw * ph;
            const int nw = (pw + 63) / 64;
            double* T = Tv.data();
            double* buf = bufv.data();
            double* w = wv.data();
            S* vc = vcv.data();
            int32_t* last = lastv.data();
            uint64_t* act = actv.data();  // pixels with last >= idx, per row
            std::fill(act, act + static_cast<size_t>(ph) * nw, 0ULL);
            for (int ly = 0; ly < ph; ++ly) {
                for (int lx = 0; lx < pw; ++lx) {
                    const int p = ly * pw + lx;
                    const int64_t pix = static_cast<int64_t>(py0 + ly) * W + (px0 + lx);
                    const double Tf = Tfinal[pix];
                    T[p] = Tf;
                    last[p] = lastids[pix];
                    order[p] = {last[p], p};
                    double acc_bg = 0.0;
                    for (int k = 0; k < D; ++k) {
                        const S v = v_col[pix * D + k];
                        vc[static_cast<size_t>(k) * cs + p] = v;
                        buf[static_cast<size_t>(k) * cs + p] = 0.0;
                        if (bg != nullptr) acc_bg += static_cast<double>(bg[k]) * v;
                    }
                    const double va = v_alpha_img != nullptr ? static_cast<double>(v_alpha_img[pix]) : 0.0;
                    w[p] = Tf * (va - acc_bg);
                }
            }
            std::sort(order.begin(), order.begin() + npix,
                      [](const std::pair<int32_t, int32_t>& u, const std::pair<int32_t, int32_t>& v) {
                          return u.first > v.first;
                      });
            int nact = 0;
            int64_t maxlast = order[0].first;
            if (maxlast >= end) maxlast = end - 1;
            for (int64_t idx = maxlast; idx >= start; --idx) {
                while (nact < npix && order[nact].first >= idx) {
                    const int p = order[nact].second;
                    const int ly = p / pw, lx = p - ly * pw;
                    act[ly * nw + (lx >> 6)] |= 1ULL << (lx & 63);
                    ++nact;
                }
                const int64_t g = ids[idx];
                if (idx - kPrefetch >= start) {  // back to front, at random in memory: fetch ahead
                    const int64_t gn = ids[idx - kPrefetch];
                    __builtin_prefetch(P + gn);
                    __builtin_prefetch(gout + static_cast<size_t>(gn) * G, 1);
                }
                const GParam<S>& q = P[g];
                const int32_t y0 = std::max(q.y0, py0), y1 = std::min(q.y1, py0 + ph - 1);
                if (y0 > y1 || q.x0 > px0 + pw - 1 || q.x1 < px0) continue;
                const S mx = q.mx, my = q.my, a = q.a, b = q.b, c = q.c, op = q.op;
                const S sthr = q.sthr;
                const S* cg = colors + g * D;
                // the sums over pixels: locals in the scalar rows, sums[] in the vector rows (a
                // Gaussian's rows are all one or all the other)
                double vmx = 0, vmy = 0, va = 0, vb = 0, vcc = 0, vop = 0;
                double* sums = sumv.data();
                double* acc_col = sums + 6;
                std::fill(sums, sums + 6 + D, 0.0);
                bool any = false;
                const bool vec = simd_rows(q, nw, D, simd_on);
                for (int32_t y = y0; y <= y1; ++y) {
                    const int ly = y - py0;
                    const uint64_t* row = act + ly * nw;
                    if (nw == 1 && row[0] == 0) continue;
                    const S dy = my - (static_cast<S>(y) + S(0.5));
                    int32_t xa, xb;
                    if (!row_span(q, static_cast<double>(dy), px0, pw, xa, xb)) continue;
                    const S cdy2 = c * dy * dy;
                    if constexpr (std::is_same<S, float>::value) {
                        if (vec) {
                            any |= clod_simd::backward_row(row, xa, xb, px0, ly * pw, mx, dy, a, b, c, op, sthr, cdy2,
                                                           cg, D, T, w, vc, buf, cs, sums);
                            continue;
                        }
                    }
                    for_bits(row, xa, xb, [&](int lx) {
                        const int p = ly * pw + lx;
                        const S dx = mx - (static_cast<S>(px0 + lx) + S(0.5));
                        const S sigma = S(0.5) * (a * dx * dx + cdy2) + b * dx * dy;
                        if (sigma > sthr) return;
                        const S vis = std::exp(-sigma);
                        const S alpha = std::min(maxA, op * vis);
                        if (sigma < S(0) || alpha < athr) return;
                        any = true;
                        const double ra = 1.0 / (1.0 - static_cast<double>(alpha));
                        const double Tp = T[p] * ra;
                        T[p] = Tp;
                        const double fac = alpha * Tp;
                        double v_alpha = ra * w[p];
                        for (int k = 0; k < D; ++k) {
                            const size_t kp = static_cast<size_t>(k) * cs + p;
                            const double v = vc[kp];
                            acc_col[k] += fac * v;
                            v_alpha += (cg[k] * Tp - buf[kp] * ra) * v;
                            buf[kp] += cg[k] * fac;
                        }
                        if (op * vis <= maxA) {
                            const double v_sigma = -static_cast<double>(op * vis) * v_alpha;
                            const double ddx = dx, ddy = dy;
                            va += 0.5 * v_sigma * ddx * ddx;
                            vb += v_sigma * ddx * ddy;
                            vcc += 0.5 * v_sigma * ddy * ddy;
                            vmx += v_sigma * (a * ddx + b * ddy);
                            vmy += v_sigma * (b * ddx + c * ddy);
                            vop += vis * v_alpha;
                        }
                    });
                }
                if (any) {
                    if (!vec) {
                        sums[0] = vmx;
                        sums[1] = vmy;
                        sums[2] = va;
                        sums[3] = vb;
                        sums[4] = vcc;
                        sums[5] = vop;
                    }
                    S* o = gout + static_cast<size_t>(g) * G;
                    for (int j = 0; j < G; ++j) o[j] += static_cast<S>(sums[j]);
                }
            }
        };
        if (!deterministic) {
#pragma omp for schedule(dynamic, 1)
            for (int64_t t = 0; t < ntiles; ++t) tile_body(t, bufs[tid].data());
        } else {
            // fixed tile -> buffer mapping, tiles in increasing order within a buffer:
            // the sums do not depend on which thread runs what, or when
#pragma omp for schedule(static, 1)
            for (int b = 0; b < nthreads; ++b) {
                std::vector<S>& db = bufs[b];
                db.assign(static_cast<size_t>(N) * G, S(0));
                for (int64_t t = b; t < ntiles; t += nthreads) tile_body(t, db.data());
            }
        }
        // reduction over threads (all buffers are complete after the barrier)
#pragma omp barrier
#pragma omp for schedule(static)
        for (int64_t g = 0; g < N; ++g) {
            S s[64];
            const int GG = std::min(G, 64);
            for (int j = 0; j < GG; ++j) s[j] = 0;
            for (int th_ = 0; th_ < nthreads; ++th_) {  // fixed order
                if (bufs[th_].empty()) continue;  // fewer threads than asked for
                const S* src = bufs[th_].data() + static_cast<size_t>(g) * G;
                for (int j = 0; j < GG; ++j) s[j] += src[j];
            }
            g_means[2 * g] = s[0];
            g_means[2 * g + 1] = s[1];
            g_conics[3 * g] = s[2];
            g_conics[3 * g + 1] = s[3];
            g_conics[3 * g + 2] = s[4];
            g_opac[g] = s[5];
            for (int k = 0; k < D; ++k) {
                if (6 + k < 64) {
                    g_colors[g * D + k] = s[6 + k];
                } else {
                    S v = 0;
                    for (int th_ = 0; th_ < nthreads; ++th_)
                        if (!bufs[th_].empty()) v += bufs[th_][static_cast<size_t>(g) * G + 6 + k];
                    g_colors[g * D + k] = v;
                }
            }
        }
    }
}

void check_inputs(
    const torch::Tensor& means2d, const torch::Tensor& conics,
    const torch::Tensor& colors, const torch::Tensor& opacities,
    const torch::Tensor& offsets, const torch::Tensor& ids) {
    TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N,2]");
    const auto N = means2d.size(0);
    TORCH_CHECK(conics.dim() == 2 && conics.size(0) == N && conics.size(1) == 3, "conics must be [N,3]");
    TORCH_CHECK(colors.dim() == 2 && colors.size(0) == N && colors.size(1) >= 1, "colors must be [N,D]");
    TORCH_CHECK(opacities.dim() == 1 && opacities.size(0) == N, "opacities must be [N]");
    TORCH_CHECK(offsets.dim() == 2 && offsets.scalar_type() == torch::kInt64, "isect_offsets must be [th,tw] int64 (internal)");
    TORCH_CHECK(ids.dim() == 1 && ids.scalar_type() == torch::kInt64, "flatten_ids must be [M] int64 (internal)");
    for (auto* t : {&means2d, &conics, &colors, &opacities, &offsets, &ids}) {
        TORCH_CHECK(t->is_contiguous() && t->device().is_cpu(), "inputs must be contiguous CPU tensors");
    }
    TORCH_CHECK(conics.scalar_type() == means2d.scalar_type() &&
                    colors.scalar_type() == means2d.scalar_type() &&
                    opacities.scalar_type() == means2d.scalar_type(),
                "all float inputs must share a dtype");
}

std::vector<torch::Tensor> composite_forward(
    torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
    torch::Tensor opacities, c10::optional<torch::Tensor> backgrounds,
    int64_t width, int64_t height, int64_t tile_size,
    torch::Tensor isect_offsets, torch::Tensor flatten_ids, int64_t num_threads, bool with_state) {
    check_inputs(means2d, conics, colors, opacities, isect_offsets, flatten_ids);
    const int64_t N = means2d.size(0);
    const int D = static_cast<int>(colors.size(1));
    const int32_t th = static_cast<int32_t>(isect_offsets.size(0));
    const int32_t tw = static_cast<int32_t>(isect_offsets.size(1));
    const auto opts = means2d.options();
    auto out_col = torch::empty({height, width, D}, opts);
    auto out_alpha = torch::empty({height, width, 1}, opts);
    // the final transmittance and last index per pixel: the backward's state (empty without it)
    const int64_t sh = with_state ? height : 0, sw = with_state ? width : 0;
    auto out_T = torch::empty({sh, sw}, opts);
    auto out_last = torch::empty({sh, sw}, opts.dtype(torch::kInt32));
    torch::Tensor bg;
    if (backgrounds.has_value() && backgrounds->defined()) {
        bg = backgrounds->contiguous();
        TORCH_CHECK(bg.numel() == D && bg.scalar_type() == means2d.scalar_type(), "backgrounds must be [D]");
    }
    const int nt = static_cast<int>(std::max<int64_t>(1, num_threads));
    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
        using S = scalar_t;
        auto run = [&](auto cd_tag) {
            constexpr int CDv = decltype(cd_tag)::value;
            forward_impl<S, CDv>(
                N, D, means2d.data_ptr<S>(), conics.data_ptr<S>(), colors.data_ptr<S>(),
                opacities.data_ptr<S>(), bg.defined() ? bg.data_ptr<S>() : nullptr,
                (int32_t)width, (int32_t)height, (int32_t)tile_size, th, tw,
                isect_offsets.data_ptr<int64_t>(), flatten_ids.data_ptr<int64_t>(), flatten_ids.numel(),
                out_col.data_ptr<S>(), out_alpha.data_ptr<S>(), with_state ? out_T.data_ptr<S>() : nullptr,
                with_state ? out_last.data_ptr<int32_t>() : nullptr, nt);
        };
        switch (D) {
            case 1: run(std::integral_constant<int, 1>()); break;
            case 2: run(std::integral_constant<int, 2>()); break;
            case 3: run(std::integral_constant<int, 3>()); break;
            case 4: run(std::integral_constant<int, 4>()); break;
            default: run(std::integral_constant<int, 0>()); break;
        }
    });
    return {out_col, out_alpha, out_T, out_last};
}

std::vector<torch::Tensor> composite_backward(
    torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
    torch::Tensor opacities, c10::optional<torch::Tensor> backgrounds,
    int64_t width, int64_t height, int64_t tile_size,
    torch::Tensor isect_offsets, torch::Tensor flatten_ids,
    torch::Tensor T_final, torch::Tensor last_ids,
    torch::Tensor v_render_colors, c10::optional<torch::Tensor> v_render_alphas,
    int64_t num_threads, bool deterministic) {
    check_inputs(means2d, conics, colors, opacities, isect_offsets, flatten_ids);
    const int64_t N = means2d.size(0);
    const int D = static_cast<int>(colors.size(1));
    const int32_t th = static_cast<int32_t>(isect_offsets.size(0));
    const int32_t tw = static_cast<int32_t>(isect_offsets.size(1));
    TORCH_CHECK(T_final.is_contiguous() && T_final.numel() == width * height, "T_final shape");
    TORCH_CHECK(last_ids.is_contiguous() && last_ids.scalar_type() == torch::kInt32, "last_ids");
    auto vcol = v_render_colors.contiguous();
    TORCH_CHECK(vcol.numel() == width * height * D && vcol.scalar_type() == means2d.scalar_type(), "v_render_colors");
    torch::Tensor valpha;
    if (v_render_alphas.has_value() && v_render_alphas->defined()) {
        valpha = v_render_alphas->contiguous();
        TORCH_CHECK(valpha.numel() == width * height && valpha.scalar_type() == means2d.scalar_type(), "v_render_alphas");
    }
    torch::Tensor bg;
    if (backgrounds.has_value() && backgrounds->defined()) {
        bg = backgrounds->contiguous();
        TORCH_CHECK(bg.numel() == D && bg.scalar_type() == means2d.scalar_type(), "backgrounds must be [D]");
    }
    auto g_means = torch::empty_like(means2d);
    auto g_conics = torch::empty_like(conics);
    auto g_colors = torch::empty_like(colors);
    auto g_opac = torch::empty_like(opacities);
    const int nt = static_cast<int>(std::max<int64_t>(1, num_threads));
    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
        using S = scalar_t;
        auto run = [&](auto cd_tag) {
            constexpr int CDv = decltype(cd_tag)::value;
            backward_impl<S, CDv>(
                N, D, means2d.data_ptr<S>(), conics.data_ptr<S>(), colors.data_ptr<S>(),
                opacities.data_ptr<S>(), bg.defined() ? bg.data_ptr<S>() : nullptr,
                (int32_t)width, (int32_t)height, (int32_t)tile_size, th, tw,
                isect_offsets.data_ptr<int64_t>(), flatten_ids.data_ptr<int64_t>(), flatten_ids.numel(),
                T_final.data_ptr<S>(), last_ids.data_ptr<int32_t>(), vcol.data_ptr<S>(),
                valpha.defined() ? valpha.data_ptr<S>() : nullptr,
                g_means.data_ptr<S>(), g_conics.data_ptr<S>(), g_colors.data_ptr<S>(),
                g_opac.data_ptr<S>(), nt, deterministic);
        };
        switch (D) {
            case 1: run(std::integral_constant<int, 1>()); break;
            case 2: run(std::integral_constant<int, 2>()); break;
            case 3: run(std::integral_constant<int, 3>()); break;
            case 4: run(std::integral_constant<int, 4>()); break;
            default: run(std::integral_constant<int, 0>()); break;
        }
    });
    return {g_means, g_conics, g_colors, g_opac};
}

}  // namespace

int64_t composite_simd(int64_t mode) { return clod_simd::set_mode(static_cast<int>(mode)); }

// lod_terms.cpp (the per-frame LoD terms; one extension, one build)
std::vector<torch::Tensor> lod_frustum_distances(torch::Tensor cols, std::vector<double> R, std::vector<double> t,
                                                 double fx, double cx, double fy, double cy, int64_t width,
                                                 int64_t height, double near_plane, std::vector<double> center);
std::tuple<torch::Tensor, int64_t, int64_t> lod_keep_cpu(torch::Tensor opacities, torch::Tensor d_norm,
                                                         torch::Tensor sigma_d, torch::Tensor frustum, double s_v, double tau, double eps,
                                                         bool with_ids);
torch::Tensor lod_mask_cpu(torch::Tensor opacities, torch::Tensor d_norm, torch::Tensor sigma_d, double s_v,
                           double tau, double eps);
torch::Tensor lod_window_opacities_cpu(torch::Tensor ids, torch::Tensor opacities, torch::Tensor logits,
                                       torch::Tensor gain, torch::Tensor d_norm, torch::Tensor sigma_d,
                                       double s_v, double level, double tau, double eps, double width);
torch::Tensor lod_critical_cpu(torch::Tensor opacities, torch::Tensor d_norm, torch::Tensor sigma_d, double tau,
                               double eps);

// tree_cut.cpp (the merge tree's cut and drawn attributes)
std::vector<torch::Tensor> tree_cut_cpu(std::vector<torch::Tensor> cols, std::vector<double> R, std::vector<double> t,
                                        double fx, double cx, double fy, double cy, int64_t width, int64_t height,
                                        double near_plane, std::vector<double> center, std::vector<torch::Tensor> sigma_d,
                                        std::vector<torch::Tensor> exits, std::vector<torch::Tensor> parents,
                                        std::vector<torch::Tensor> leads, double s, double F, double M);
std::vector<torch::Tensor> tree_terms_cpu(std::vector<torch::Tensor> d_norm, std::vector<torch::Tensor> sigma_d,
                                          std::vector<torch::Tensor> exits, std::vector<torch::Tensor> parents,
                                          std::vector<torch::Tensor> leads, double F);
double tree_budget_cpu(std::vector<torch::Tensor> E, std::vector<torch::Tensor> U,
                       std::vector<torch::Tensor> weights, double k);
std::vector<torch::Tensor> tree_frame_cpu(std::vector<torch::Tensor> cols, std::vector<double> R, std::vector<double> t,
                                          double fx, double cx, double fy, double cy, int64_t width, int64_t height,
                                          double near_plane, std::vector<double> center);
std::vector<torch::Tensor> tree_attributes_cpu(std::vector<torch::Tensor> attrs, std::vector<torch::Tensor> ids,
                                               std::vector<torch::Tensor> ws, std::vector<torch::Tensor> fades,
                                               std::vector<torch::Tensor> parents, std::vector<torch::Tensor> leads,
                                               double shrink_floor, std::vector<double> campos, int64_t sh_degree);

std::vector<torch::Tensor> tree_budget_events_cpu(std::vector<torch::Tensor> E, std::vector<torch::Tensor> U);
std::vector<torch::Tensor> tree_budget_walk_cpu(std::vector<torch::Tensor> E, std::vector<torch::Tensor> U,
                                                std::vector<torch::Tensor> fade, torch::Tensor pos, torch::Tensor node,
                                                torch::Tensor hi, std::vector<torch::Tensor> frustum, double k, double M);

// splat_cost.cpp (the "ellipse_px" cost of every Gaussian, lod.cost.splat_cost)
torch::Tensor splat_cost_cpu(torch::Tensor means, torch::Tensor quats, torch::Tensor scales, torch::Tensor opacities,
                             std::vector<double> R, std::vector<double> t, double fx, double cx, double fy, double cy,
                             int64_t width, int64_t height, double near_plane, double far_plane, double eps2d);
int64_t ordered_prefix_count_cpu(torch::Tensor scores, torch::Tensor weights, double budget);

// projection.cpp (the EWA projection of a frame without gradients, render.projection's two stages)
std::vector<torch::Tensor> project_geometry_cpu(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                                torch::Tensor keep, std::vector<double> R, std::vector<double> t,
                                                double fx, double cx, double fy, double cy, int64_t width,
                                                int64_t height, double near_plane, double far_plane);
std::vector<torch::Tensor> finish_projection_cpu(torch::Tensor means2d, torch::Tensor aa, torch::Tensor ab,
                                                 torch::Tensor bb, torch::Tensor axb2, torch::Tensor opacities,
                                                 torch::Tensor cov_scale, int64_t width, int64_t height, double eps2d,
                                                 double radius_clip);

// sh_colors.cpp (the rasteriser's colours from SH, render.cpu.sh_colors)
torch::Tensor sh_colors_cpu(torch::Tensor means, torch::Tensor coeffs, std::vector<double> campos, int64_t degree);
torch::Tensor sh_colors_rows_cpu(torch::Tensor means, torch::Tensor sh0, torch::Tensor shN, torch::Tensor ids,
                                 std::vector<double> campos, int64_t degree);
std::vector<torch::Tensor> sh_colors_backward_cpu(torch::Tensor means, torch::Tensor coeffs, std::vector<double> campos,
                                                  int64_t degree, torch::Tensor v_colors);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.def("forward", &composite_forward, "CPU Gaussian compositor forward");
    m.def("backward", &composite_backward, "CPU Gaussian compositor backward");
    m.def("composite_simd", &composite_simd,
          "the compositor's vector rows: -1 asks, 0 turns them off (the scalar twin), 1 on where the CPU has them; "
          "returns whether they run");
    m.def("lod_frustum_distances", &lod_frustum_distances, "frustum test and d' of the LoD (lod.frame_terms)");
    m.def("lod_mask", &lod_mask_cpu, "Eq. 2 mask alpha'' > tau s_v (lod.lod_mask)");
    m.def("lod_keep", &lod_keep_cpu, "ids of Eq. 2's mask and the frustum counts (lod.lod_keep)");
    m.def("lod_window_opacities", &lod_window_opacities_cpu, "the window fade's drawn opacities (lod.window_opacities)");
    m.def("lod_critical", &lod_critical_cpu, "the critical s_v of each Gaussian (budget.critical_s_v)");
    m.def("tree_cut", &tree_cut_cpu, "the merge tree's cut at one s_v, walked from the roots (tree.walk)");
    m.def("tree_terms", &tree_terms_cpu, "every node's entry, end and fade (tree.terms)");
    m.def("tree_budget", &tree_budget_cpu, "the level a budget draws (tree.budget_s_v)");
    m.def("tree_budget_events", &tree_budget_events_cpu, "a budget's interval ends sorted, coarsest first");
    m.def("tree_budget_walk", &tree_budget_walk_cpu, "a count budget's level and cut from cached terms and ends");
    m.def("tree_frame", &tree_frame_cpu, "every node's frustum test and d' (tree.frame)");
    m.def("tree_attributes", &tree_attributes_cpu, "a cut's drawn attributes (tree.cut_attributes)");
    m.def("project_geometry", &project_geometry_cpu, "depth cull and raw 2D covariance terms (projection.project_geometry)");
    m.def("finish_projection", &finish_projection_cpu, "eps2d blur, conics, radii and culls (projection.finish_projection)");
    m.def("sh_colors", &sh_colors_cpu, "colours of SH coefficients from a camera centre (render.cpu.sh_colors)");
    m.def("sh_colors_rows", &sh_colors_rows_cpu, "colours of some rows of sh0 / shN, read in place (cpu.sh_colors_rows)");
    m.def("sh_colors_backward", &sh_colors_backward_cpu, "the gradients of sh_colors (means, coefficients)");
    m.def("splat_cost", &splat_cost_cpu, "every Gaussian's ellipse_px cost (lod.cost.splat_cost at level 0)");
    m.def("ordered_prefix_count", &ordered_prefix_count_cpu,
          "the longest prefix of an order whose weights fit a budget (lod.cost.ordered_prefix_count)");
}
