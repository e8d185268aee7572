// The rasteriser's colours: [V, 3] from SH coefficients [V, K, 3] seen from the camera centre, in
// one pass over the rows. Twin: clod_adapter.render.cpu.sh_colors (its torch form: about 40
// elementwise operations and a batched product over [V]); tests/test_sh.py holds them together.
// clod_sh::rgb is also tree_cut.cpp's (a cut's drawn colours), declared there.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace clod_sh {

// The real SH bases of clod_adapter.render.sh.sh_bases (degree 0..3; Sloan, JCGT 2013, gsplat
// 1.5.3's signs and order) at the unit direction of dir = mean - campos (any length; normalised
// here, its norm at least 1e-12, as the twin): b[0 .. nb), nb = (degree + 1)^2 returned; u[3]
// the unit direction and *norm its length (degree >= 1 only).
template <typename S>
int bases(int degree, S dx, S dy, S dz, S* b, S* u, S* norm) {
    b[0] = S(0.2820947917738781);
    if (degree < 1) return 1;
    const S n = std::max(std::sqrt(dx * dx + dy * dy + dz * dz), S(1e-12));
    const S x = dx / n, y = dy / n, z = dz / n;
    u[0] = x, u[1] = y, u[2] = z, *norm = n;
    const S c1 = S(0.48860251190292);
    b[1] = -c1 * y;
    b[2] = c1 * z;
    b[3] = -c1 * x;
    if (degree < 2) return 4;
    const S z2 = z * z, tB = S(-1.092548430592079) * z, fC1 = x * x - y * y, fS1 = S(2) * x * y;
    b[4] = S(0.5462742152960395) * fS1;
    b[5] = tB * y;
    b[6] = S(0.9461746957575601) * z2 - S(0.3153915652525201);
    b[7] = tB * x;
    b[8] = S(0.5462742152960395) * fC1;
    if (degree < 3) return 9;
    const S tC = S(-2.285228997322329) * z2 + S(0.4570457994644658), tB3 = S(1.445305721320277) * z;
    const S fC2 = x * fC1 - y * fS1, fS2 = x * fS1 + y * fC1;
    b[9] = S(-0.5900435899266435) * fS2;
    b[10] = tB3 * fS1;
    b[11] = tC * y;
    b[12] = z * (S(1.865881662950577) * z2 - S(1.119528997770346));
    b[13] = tC * x;
    b[14] = tB3 * fC1;
    b[15] = S(-0.5900435899266435) * fC2;
    return 16;
}

// each channel's sum over the bases, in order: the colour before the offset and the clamp
template <typename S>
void sums(int nb, const S* b, const S* coeffs, S* v) {
    v[0] = v[1] = v[2] = S(0);
    for (int k = 0; k < nb; ++k) {
        v[0] += b[k] * coeffs[3 * k];
        v[1] += b[k] * coeffs[3 * k + 1];
        v[2] += b[k] * coeffs[3 * k + 2];
    }
}

// View-dependent colour of real SH coefficients (degree 0..3), gsplat 1.5.3's spherical_harmonics
// + rendering.py's clamp_min(sh + 0.5, 0): out[3] = max(sum_b basis_b(dir) coeffs[b][c] + 0.5, 0);
// coeffs: [(degree + 1)^2][3] row-major; dir = mean - campos (bases).
template <typename S>
void rgb(int degree, const S* coeffs, S dx, S dy, S dz, S* out) {
    S b[16], u[3], n, v[3];
    sums(bases(degree, dx, dy, dz, b, u, &n), b, coeffs, v);
    for (int c = 0; c < 3; ++c) out[c] = std::max(v[c] + S(0.5), S(0));
}

// The vector-Jacobian product of rgb: given v_out[3] (the gradient of the clamped colour), adds
// the coefficients' gradient to v_coeffs[(degree + 1)^2][3] and returns the direction's in v_dir[3]
// (through the normalisation), as autograd differentiates the twin: the clamp passes where
// sum + 0.5 >= 0 (torch's clamp_min), the bases' derivatives are those of sh_bases' polynomials.
template <typename S>
void rgb_vjp(int degree, const S* coeffs, S dx, S dy, S dz, const S* v_out, S* v_coeffs, S* v_dir) {
    S b[16], u[3], n = S(1), v[3], g[3];
    const int nb = bases(degree, dx, dy, dz, b, u, &n);
    sums(nb, b, coeffs, v);
    for (int c = 0; c < 3; ++c) g[c] = v[c] + S(0.5) >= S(0) ? v_out[c] : S(0);
    for (int k = 0; k < nb; ++k)
        for (int c = 0; c < 3; ++c) v_coeffs[3 * k + c] += b[k] * g[c];
    v_dir[0] = v_dir[1] = v_dir[2] = S(0);
    if (degree < 1) return;
    const S x = u[0], y = u[1], z = u[2];
    S w[16];  // w[k] = sum_c g[c] coeffs[k][c]: the gradient of each basis
    for (int k = 0; k < nb; ++k) w[k] = g[0] * coeffs[3 * k] + g[1] * coeffs[3 * k + 1] + g[2] * coeffs[3 * k + 2];
    const S c1 = S(0.48860251190292);
    S vx = -c1 * w[3], vy = -c1 * w[1], vz = c1 * w[2];
    if (degree >= 2) {
        const S a = S(0.5462742152960395), t = S(-1.092548430592079);
        vx += a * S(2) * y * w[4] + t * z * w[7] + a * S(2) * x * w[8];
        vy += a * S(2) * x * w[4] + t * z * w[5] - a * S(2) * y * w[8];
        vz += t * y * w[5] + S(2) * S(0.9461746957575601) * z * w[6] + t * x * w[7];
    }
    if (degree >= 3) {
        const S p = S(-0.5900435899266435), q = S(1.445305721320277), r = S(-2.285228997322329);
        const S z2 = z * z, fC1 = x * x - y * y, fS1 = S(2) * x * y, tC = r * z2 + S(0.4570457994644658);
        const S x2y2 = S(3) * fC1, xy6 = S(6) * x * y;
        vx += p * xy6 * w[9] + q * z * S(2) * y * w[10] + tC * w[13] + q * z * S(2) * x * w[14] + p * x2y2 * w[15];
        vy += p * x2y2 * w[9] + q * z * S(2) * x * w[10] + tC * w[11] - q * z * S(2) * y * w[14] - p * xy6 * w[15];
        vz += q * fS1 * w[10] + r * S(2) * z * y * w[11] + (S(3) * S(1.865881662950577) * z2 - S(1.119528997770346)) * w[12] +
              r * S(2) * z * x * w[13] + q * fC1 * w[14];
    }
    // through the normalisation: (v - u (u . v)) / |dir|
    const S dot = x * vx + y * vy + z * vz;
    v_dir[0] = (vx - x * dot) / n, v_dir[1] = (vy - y * dot) / n, v_dir[2] = (vz - z * dot) / n;
}

template void rgb<float>(int, const float*, float, float, float, float*);
template void rgb<double>(int, const double*, double, double, double, double*);
template void rgb_vjp<float>(int, const float*, float, float, float, const float*, float*, float*);
template void rgb_vjp<double>(int, const double*, double, double, double, const double*, double*, double*);

}  // namespace clod_sh

namespace {

constexpr int64_t kGrainSh = 4096;  // ~50 multiply-adds a row at degree 3

// the rows' shapes (means [V, 3], coeffs [V, K >= (degree + 1)^2, 3], campos [3]), or a TORCH_CHECK
void check_rows(const torch::Tensor& means, const torch::Tensor& coeffs, const std::vector<double>& campos,
                int64_t degree, const char* name) {
    TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && coeffs.dim() == 3 && coeffs.size(0) == means.size(0) &&
                    coeffs.size(2) == 3 && degree >= 0 && degree <= 3 && coeffs.size(1) >= (degree + 1) * (degree + 1) &&
                    campos.size() == 3,
                name, ": means [V, 3], coeffs [V, K >= (degree + 1)^2, 3], degree 0..3, campos 3 values");
}

// fn(row, its coefficients, its direction from the camera centre) over every row, in parallel
template <typename S, typename Fn>
void each_row(const torch::Tensor& m, const torch::Tensor& c, const std::vector<double>& campos, Fn&& fn) {
    const S* mp = m.data_ptr<S>();
    const S* cp = c.data_ptr<S>();
    const int64_t K = c.size(1);
    const S cx = static_cast<S>(campos[0]), cy = static_cast<S>(campos[1]), cz = static_cast<S>(campos[2]);
    at::parallel_for(0, m.size(0), kGrainSh, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i) fn(i, cp + i * K * 3, mp[3 * i] - cx, mp[3 * i + 1] - cy, mp[3 * i + 2] - cz);
    });
}

}  // namespace

torch::Tensor sh_colors_cpu(torch::Tensor means, torch::Tensor coeffs, std::vector<double> campos, int64_t degree) {
    check_rows(means, coeffs, campos, degree, "sh_colors");
    auto m = means.contiguous();
    auto c = coeffs.contiguous();
    auto out = torch::empty({m.size(0), 3}, m.options());
    AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "sh_colors", [&] {
        scalar_t* op = out.data_ptr<scalar_t>();
        each_row<scalar_t>(m, c, campos, [&](int64_t i, const scalar_t* co, scalar_t dx, scalar_t dy, scalar_t dz) {
            clod_sh::rgb<scalar_t>(static_cast<int>(degree), co, dx, dy, dz, op + 3 * i);
        });
    });
    return out;
}

// sh_colors_cpu of the rows ids [V] of a model whose SH is stored as sh0 [N, 1, 3] and shN [N, K-1, 3]
// (render.cpu.sh_colors_rows): each row's coefficients read in place, no [V, K, 3] gather
torch::Tensor sh_colors_rows_cpu(torch::Tensor means, torch::Tensor sh0, torch::Tensor shN, torch::Tensor ids,
                                 std::vector<double> campos, int64_t degree) {
    const int64_t n = means.size(0), KR = shN.dim() == 3 ? shN.size(1) : -1;
    TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && sh0.dim() == 3 && sh0.size(0) == n && sh0.size(1) == 1 &&
                    sh0.size(2) == 3 && shN.dim() == 3 && shN.size(0) == n && shN.size(2) == 3 && KR <= 15 &&
                    degree >= 0 && degree <= 3 && KR + 1 >= (degree + 1) * (degree + 1) && campos.size() == 3 &&
                    ids.dim() == 1 && ids.scalar_type() == torch::kInt64 &&
                    sh0.scalar_type() == means.scalar_type() && shN.scalar_type() == means.scalar_type(),
                "sh_colors_rows: means [N, 3], sh0 [N, 1, 3], shN [N, K-1, 3] (K <= 16, >= (degree + 1)^2) of one "
                "dtype, int64 ids [V], degree 0..3, campos 3 values");
    auto m = means.contiguous();
    auto c0 = sh0.contiguous();
    auto cN = shN.contiguous();
    auto id = ids.contiguous();
    const int64_t v = id.numel();
    auto out = torch::empty({v, 3}, m.options());
    AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "sh_colors_rows", [&] {
        using S = scalar_t;
        const S *mp = m.data_ptr<S>(), *p0 = c0.data_ptr<S>(), *pN = cN.data_ptr<S>();
        const int64_t* ip = id.data_ptr<int64_t>();
        S* op = out.data_ptr<S>();
        const S cx = static_cast<S>(campos[0]), cy = static_cast<S>(campos[1]), cz = static_cast<S>(campos[2]);
        for (int64_t j = 0; j < v; ++j) TORCH_CHECK(ip[j] >= 0 && ip[j] < n, "sh_colors_rows: row ", ip[j], " outside [0, ", n, ")");
        at::parallel_for(0, v, kGrainSh, [&](int64_t b, int64_t e) {
            S row[48];
            for (int64_t j = b; j < e; ++j) {
                const int64_t i = ip[j];
                std::copy(p0 + 3 * i, p0 + 3 * i + 3, row);
                std::copy(pN + i * KR * 3, pN + (i + 1) * KR * 3, row + 3);
                clod_sh::rgb<S>(static_cast<int>(degree), row, mp[3 * i] - cx, mp[3 * i + 1] - cy, mp[3 * i + 2] - cz,
                                op + 3 * j);
            }
        });
    });
    return out;
}

// the backward of sh_colors_cpu: (v_means [V, 3], v_coeffs [V, K, 3]) from v_colors [V, 3]
std::vector<torch::Tensor> sh_colors_backward_cpu(torch::Tensor means, torch::Tensor coeffs, std::vector<double> campos,
                                                  int64_t degree, torch::Tensor v_colors) {
    check_rows(means, coeffs, campos, degree, "sh_colors_backward");
    TORCH_CHECK(v_colors.sizes() == means.sizes(), "sh_colors_backward: v_colors must be [V, 3]");
    auto m = means.contiguous();
    auto c = coeffs.contiguous();
    auto v = v_colors.to(m.scalar_type()).contiguous();
    const int64_t K = c.size(1);
    auto v_means = torch::empty_like(m);
    auto v_coeffs = torch::zeros_like(c);
    AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "sh_colors_backward", [&] {
        const scalar_t* vp = v.data_ptr<scalar_t>();
        scalar_t* vm = v_means.data_ptr<scalar_t>();
        scalar_t* vc = v_coeffs.data_ptr<scalar_t>();
        each_row<scalar_t>(m, c, campos, [&](int64_t i, const scalar_t* co, scalar_t dx, scalar_t dy, scalar_t dz) {
            clod_sh::rgb_vjp<scalar_t>(static_cast<int>(degree), co, dx, dy, dz, vp + 3 * i, vc + i * K * 3, vm + 3 * i);
        });
    });
    return {v_means, v_coeffs};
}
