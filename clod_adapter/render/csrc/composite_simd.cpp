// SIMD rows of the CPU compositor (composite.cpp): four pixels of one tile row at once, for one
// Gaussian, in float, on x86-64 CPUs with AVX2 and FMA, built by GCC (selected at run time; the
// scalar kernel in composite.cpp is the twin and runs everywhere else).
//
// Bit-identical to the scalar kernel by construction:
//   * every lane evaluates the scalar expressions with the same operations in the same order
//     (explicit mul/add intrinsics, no contraction; -ffp-contract=off holds for the scalar code);
//   * exp is glibc's expf (sysdeps/ieee754/flt-32/e_expf.c, from ARM optimized-routines: a
//     32-entry table of 2^(i/32) and a cubic in double) in the FMA form glibc's x86-64 ifunc
//     selects on CPUs with FMA; active() checks it against this process's std::exp before any
//     use and falls back to the scalar kernel on a mismatch (another libm, another variant);
//   * the backward's per-Gaussian sums over pixels are added lane by lane in pixel order
//     (lanes that do not contribute add +0.0, which leaves a sum that starts at +0.0 unchanged).
#include <cstdint>
#include <cstring>
#include <cmath>

// GCC only: the vector code is compiled under `#pragma GCC target`, which clang does not honour
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
#define CLOD_SIMD_X86 1
#endif

namespace clod_simd {

#ifdef CLOD_SIMD_X86

namespace {

uint64_t EXP_TAB[32];  // bits of 2^(i/32) less i << 47 (the exponent the index adds back)
constexpr double EXP_N = 32.0;
constexpr double INV_LN2_N = 0x1.71547652b82fep+0 * EXP_N;
constexpr double EXP_SHIFT = 0x1.8p+52;
constexpr double EXP_C0 = 0x1.c6af84b912394p-5 / EXP_N / EXP_N / EXP_N;
constexpr double EXP_C1 = 0x1.ebfce50fac4f3p-3 / EXP_N / EXP_N;
constexpr double EXP_C2 = 0x1.62e42ff0c52d6p-1 / EXP_N;

#pragma GCC push_options
#pragma GCC target("avx2,fma")

// expf of four floats, for |x| < 88 (the kernels use it on x in [-88, 0]; other lanes are masked)
inline __m128 exp4(__m128 x) {
    const __m256d xd = _mm256_cvtps_pd(x);
    const __m256d inv = _mm256_set1_pd(INV_LN2_N), shift = _mm256_set1_pd(EXP_SHIFT);
    __m256d kd = _mm256_fmadd_pd(inv, xd, shift);
    const __m256i ki = _mm256_castpd_si256(kd);
    kd = _mm256_sub_pd(kd, shift);
    const __m256d r = _mm256_fmsub_pd(inv, xd, kd);
    const __m256i idx = _mm256_and_si256(ki, _mm256_set1_epi64x(31));
    __m256i t = _mm256_i64gather_epi64(reinterpret_cast<const long long*>(EXP_TAB), idx, 8);
    t = _mm256_add_epi64(t, _mm256_slli_epi64(ki, 47));
    const __m256d s = _mm256_castsi256_pd(t);
    const __m256d z = _mm256_fmadd_pd(_mm256_set1_pd(EXP_C0), r, _mm256_set1_pd(EXP_C1));
    __m256d y = _mm256_fmadd_pd(_mm256_set1_pd(EXP_C2), r, _mm256_set1_pd(1.0));
    y = _mm256_fmadd_pd(z, _mm256_mul_pd(r, r), y);
    return _mm256_cvtpd_ps(_mm256_mul_pd(y, s));
}

bool exp_matches_libm() {
    // the two values that tell glibc's FMA form from its plain one, then a sweep of [-87, 87]
    volatile float probe[2] = {-0x1.f8cbb2p+5f, 0x1.04845ep+5f};
    float xs[4], got[4];
    auto check4 = [&]() {
        _mm_storeu_ps(got, exp4(_mm_loadu_ps(xs)));
        for (int i = 0; i < 4; ++i) {
            volatile float xi = xs[i];
            const float want = std::exp(static_cast<float>(xi));
            if (std::memcmp(&want, &got[i], 4) != 0) return false;
        }
        return true;
    };
    xs[0] = probe[0];
    xs[1] = probe[1];
    xs[2] = xs[3] = 0.0f;
    if (!check4()) return false;
    int n = 0;
    for (float x = -87.0f; x <= 87.0f;) {
        xs[n++] = x;
        if (n == 4) {
            if (!check4()) return false;
            n = 0;
        }
        uint32_t u;
        std::memcpy(&u, &x, 4);
        u = x < 0 ? u - 997 : u + 997;  // every 997th float (about 2 million)
        if (x < 0 && u < 0x80000000u) u = 0;  // crossed zero
        std::memcpy(&x, &u, 4);
    }
    return true;
}

#pragma GCC pop_options

bool supported() {
    __builtin_cpu_init();
    if (!__builtin_cpu_supports("avx2") || !__builtin_cpu_supports("fma")) return false;
    for (int i = 0; i < 32; ++i) {
        const double v = std::exp2(i / 32.0);
        uint64_t u;
        std::memcpy(&u, &v, 8);
        EXP_TAB[i] = u - (static_cast<uint64_t>(i) << 47);
    }
    return exp_matches_libm();
}

int g_mode = 1;  // 1: use the vector rows where supported; 0: the scalar kernel only

}  // namespace

bool available() {
    static const bool ok = supported();
    return ok;
}

bool active() { return g_mode == 1 && available(); }

int set_mode(int mode) {
    if (mode == 0 || mode == 1) g_mode = mode;
    return active() ? 1 : 0;
}

#pragma GCC push_options
#pragma GCC target("avx2,fma")

namespace {
inline __m128 lane_mask(unsigned m) {
    const __m128i bits = _mm_setr_epi32(1, 2, 4, 8);
    return _mm_castsi128_ps(_mm_cmpeq_epi32(_mm_and_si128(_mm_set1_epi32(static_cast<int>(m)), bits), bits));
}

// bits of the row's pixels lx .. lx + 3 that are live and within [.., xb]
inline unsigned live_bits(uint64_t word, int lx, int xb) {
    unsigned m = static_cast<unsigned>(word >> lx) & 0xFu;
    const int left = xb - lx;
    if (left < 3) m &= (1u << (left + 1)) - 1u;
    return m;
}

// sigma of four pixels (the scalar: 0.5 (a dx dx + c dy dy) + b dx dy, in that order)
inline __m128 sigma4(int px, float mx, float dy, float a, float b, float cdy2, __m128& dx) {
    const __m128 half = _mm_set1_ps(0.5f);
    const __m128 pxf = _mm_add_ps(_mm_cvtepi32_ps(_mm_add_epi32(_mm_set1_epi32(px), _mm_setr_epi32(0, 1, 2, 3))), half);
    dx = _mm_sub_ps(_mm_set1_ps(mx), pxf);
    const __m128 va = _mm_set1_ps(a), vb = _mm_set1_ps(b);
    return _mm_add_ps(_mm_mul_ps(half, _mm_add_ps(_mm_mul_ps(_mm_mul_ps(va, dx), dx), _mm_set1_ps(cdy2))),
                      _mm_mul_ps(_mm_mul_ps(vb, dx), _mm_set1_ps(dy)));
}
// The lanes of pixels px .. px + 3 (live bits m) that the scalar kernel draws: sigma within the
// skip threshold, sigma >= 0 and alpha >= 1/255 (its three skips, in its order, NaN as it treats
// NaN), with every lane's dx, exp(-sigma) and alpha. No lane when none passes the first skip.
inline __m128 drawn_lanes(unsigned m, int px, float mx, float dy, float a, float b, float op, float sthr,
                          float cdy2, __m128& dx, __m128& vis, __m128& alpha) {
    const __m128 sigma = sigma4(px, mx, dy, a, b, cdy2, dx);
    const __m128 ok = _mm_and_ps(lane_mask(m), _mm_cmp_ps(sigma, _mm_set1_ps(sthr), _CMP_NGT_UQ));
    if (!_mm_movemask_ps(ok)) return ok;
    vis = exp4(_mm_xor_ps(sigma, _mm_set1_ps(-0.0f)));
    alpha = _mm_min_ps(_mm_mul_ps(_mm_set1_ps(op), vis), _mm_set1_ps(0.999f));
    return _mm_and_ps(ok, _mm_and_ps(_mm_cmp_ps(sigma, _mm_setzero_ps(), _CMP_NLT_UQ),
                                     _mm_cmp_ps(alpha, _mm_set1_ps(1.0f / 255.0f), _CMP_NLT_UQ)));
}
}  // namespace

int forward_row(uint64_t* wrow, int xa, int xb, int px0, int pbase, float mx, float dy, float a, float b,
                float op, float sthr, float cdy2, const float* cg, int D, float* T, float* col, int cs,
                int32_t* last, int32_t idx) {
    const __m128 one = _mm_set1_ps(1.0f), tthr = _mm_set1_ps(1e-4f);
    int ndone = 0;
    for (int lx = xa; lx <= xb; lx += 4) {
        const unsigned m = live_bits(wrow[0], lx, xb);
        if (!m) continue;
        __m128 dx, vis, alpha;
        const __m128 ok = drawn_lanes(m, px0 + lx, mx, dy, a, b, op, sthr, cdy2, dx, vis, alpha);
        if (!_mm_movemask_ps(ok)) continue;
        const int p = pbase + lx;
        const __m128 Tp = _mm_loadu_ps(T + p);
        const __m128 nT = _mm_mul_ps(Tp, _mm_sub_ps(one, alpha));
        const __m128 done = _mm_and_ps(ok, _mm_cmp_ps(nT, tthr, _CMP_LE_OQ));
        const int dm = _mm_movemask_ps(done);
        if (dm) {
            wrow[0] &= ~(static_cast<uint64_t>(dm) << lx);
            ndone += __builtin_popcount(static_cast<unsigned>(dm));
        }
        const __m128 add = _mm_andnot_ps(done, ok);
        if (!_mm_movemask_ps(add)) continue;
        const __m128 w = _mm_mul_ps(alpha, Tp);  // the scalar kernel's vis
        for (int k = 0; k < D; ++k) {
            float* ck = col + static_cast<size_t>(k) * cs + p;
            const __m128 c0 = _mm_loadu_ps(ck);
            _mm_storeu_ps(ck, _mm_blendv_ps(c0, _mm_add_ps(c0, _mm_mul_ps(_mm_set1_ps(cg[k]), w)), add));
        }
        const __m128i l0 = _mm_loadu_si128(reinterpret_cast<const __m128i*>(last + p));
        _mm_storeu_si128(reinterpret_cast<__m128i*>(last + p),
                         _mm_blendv_epi8(l0, _mm_set1_epi32(idx), _mm_castps_si128(add)));
        _mm_storeu_ps(T + p, _mm_blendv_ps(Tp, nT, add));
    }
    return ndone;
}

bool backward_row(const uint64_t* row, int xa, int xb, int px0, int pbase, float mx, float dy, float a, float b,
                  float c, float op, float sthr, float cdy2, const float* cg, int D, double* T, const double* w,
                  const float* vc, double* buf, int cs, double* sums) {
    const __m128 maxA = _mm_set1_ps(0.999f), vop = _mm_set1_ps(op);
    const __m256d one = _mm256_set1_pd(1.0), half = _mm256_set1_pd(0.5), negd = _mm256_set1_pd(-0.0);
    const __m256d ddy = _mm256_set1_pd(static_cast<double>(dy)), da = _mm256_set1_pd(static_cast<double>(a));
    const __m256d db = _mm256_set1_pd(static_cast<double>(b)), dc = _mm256_set1_pd(static_cast<double>(c));
    alignas(32) double terms[6 + 16][4];
    bool any = false;
    for (int lx = xa; lx <= xb; lx += 4) {
        const unsigned m = live_bits(row[0], lx, xb);
        if (!m) continue;
        __m128 dx, vis, alpha;
        const __m128 ok = drawn_lanes(m, px0 + lx, mx, dy, a, b, op, sthr, cdy2, dx, vis, alpha);
        if (!_mm_movemask_ps(ok)) continue;
        const __m128 opvis = _mm_mul_ps(vop, vis);
        any = true;
        const __m256d okd = _mm256_castsi256_pd(_mm256_cvtepi32_epi64(_mm_castps_si128(ok)));
        const __m128 inner = _mm_and_ps(ok, _mm_cmp_ps(opvis, maxA, _CMP_LE_OQ));
        const __m256d innerd = _mm256_castsi256_pd(_mm256_cvtepi32_epi64(_mm_castps_si128(inner)));
        const int p = pbase + lx;
        const __m256d alpha_d = _mm256_cvtps_pd(alpha);
        const __m256d ra = _mm256_div_pd(one, _mm256_sub_pd(one, alpha_d));
        const __m256d T0 = _mm256_loadu_pd(T + p);
        const __m256d Tp = _mm256_mul_pd(T0, ra);
        _mm256_storeu_pd(T + p, _mm256_blendv_pd(T0, Tp, okd));
        const __m256d fac = _mm256_mul_pd(alpha_d, Tp);
        __m256d v_alpha = _mm256_mul_pd(ra, _mm256_loadu_pd(w + p));
        for (int k = 0; k < D; ++k) {
            const __m256d v = _mm256_cvtps_pd(_mm_loadu_ps(vc + static_cast<size_t>(k) * cs + p));
            _mm256_store_pd(terms[6 + k], _mm256_and_pd(_mm256_mul_pd(fac, v), okd));
            const __m256d cgk = _mm256_set1_pd(static_cast<double>(cg[k]));
            double* bk = buf + static_cast<size_t>(k) * cs + p;
            const __m256d b0 = _mm256_loadu_pd(bk);
            const __m256d dv = _mm256_sub_pd(_mm256_mul_pd(cgk, Tp), _mm256_mul_pd(b0, ra));
            v_alpha = _mm256_add_pd(v_alpha, _mm256_mul_pd(dv, v));
            _mm256_storeu_pd(bk, _mm256_blendv_pd(b0, _mm256_add_pd(b0, _mm256_mul_pd(cgk, fac)), okd));
        }
        const __m256d v_sigma = _mm256_mul_pd(_mm256_xor_pd(_mm256_cvtps_pd(opvis), negd), v_alpha);
        const __m256d ddx = _mm256_cvtps_pd(dx);
        const __m256d hvs = _mm256_mul_pd(half, v_sigma);
        // the order of the scalar kernel's sums: vmx vmy va vb vcc vop, then the colours
        const __m256d gx = _mm256_add_pd(_mm256_mul_pd(da, ddx), _mm256_mul_pd(db, ddy));
        const __m256d gy = _mm256_add_pd(_mm256_mul_pd(db, ddx), _mm256_mul_pd(dc, ddy));
        _mm256_store_pd(terms[0], _mm256_and_pd(_mm256_mul_pd(v_sigma, gx), innerd));
        _mm256_store_pd(terms[1], _mm256_and_pd(_mm256_mul_pd(v_sigma, gy), innerd));
        _mm256_store_pd(terms[2], _mm256_and_pd(_mm256_mul_pd(_mm256_mul_pd(hvs, ddx), ddx), innerd));
        _mm256_store_pd(terms[3], _mm256_and_pd(_mm256_mul_pd(_mm256_mul_pd(v_sigma, ddx), ddy), innerd));
        _mm256_store_pd(terms[4], _mm256_and_pd(_mm256_mul_pd(_mm256_mul_pd(hvs, ddy), ddy), innerd));
        _mm256_store_pd(terms[5], _mm256_and_pd(_mm256_mul_pd(_mm256_cvtps_pd(vis), v_alpha), innerd));
        const int nt = 6 + D;
        for (int i = 0; i < 4; ++i)
            for (int j = 0; j < nt; ++j) sums[j] += terms[j][i];
    }
    return any;
}

#pragma GCC pop_options

#else  // not x86-64 GCC: the scalar kernel only

bool active() { return false; }
int set_mode(int) { return 0; }
int forward_row(uint64_t*, int, int, int, int, float, float, float, float, float, float, float, const float*, int,
                float*, float*, int, int32_t*, int32_t) {
    return 0;
}
bool backward_row(const uint64_t*, int, int, int, int, float, float, float, float, float, float, float, float,
                  const float*, int, double*, const double*, const float*, double*, int, double*) {
    return false;
}

#endif

}  // namespace clod_simd
