// EWA projection of 3D Gaussians for a frame without gradients, in its two stages: the depth cull
// and the raw 2D covariance terms (project_geometry), then the eps2d blur, conics, radii and the
// radius and box culls (finish_projection). gsplat 1.5.3's fully_fused_projection (classic mode):
// the Jacobian at x/z, y/z clamped to 1.3x the field of view, means2d from the unclamped mean, the
// opacity-aware extent min(3.33, sqrt(2 log(255 opacity))), radii ceil(extend sqrt(cov_ii)).
//
// Twins: clod_adapter.render.projection.project_geometry and finish_projection (plain torch, the
// path every frame with gradients takes); tests/test_projection.py holds them together. As some 60
// torch operations over every row they took a sixth of a full-detail frame on 2 cores; here it is
// one loop. Arithmetic in double, stored in the inputs' dtype (the twins compute in that dtype, so
// a radius on an integer boundary may round to the other side); the determinant is the twins'
// cancellation-free |A x B|^2 + eps (|A|^2 + |B|^2) + eps^2.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace clod_ewa {  // also splat_cost.cpp's (declared there)

extern const double kAlphaThreshold = 1.0 / 255.0;  // projection.ALPHA_THRESHOLD
extern const double kExtend = 3.33;                 // projection.GAUSSIAN_EXTEND
extern const double kMaxRadius = 1073741824.0;      // projection.MAX_RADIUS (2^30)

// the camera as terms() reads it: R [9] row-major, t [3], fx, cx, fy, cy, and the limits of x/z,
// y/z for the Jacobian (gsplat's 1.3x the field of view): x_pos, x_neg, y_pos, y_neg (20 values)
void camera(const double* R, const double* t, double fx, double cx, double fy, double cy, double width,
            double height, double* cam) {
    std::copy(R, R + 9, cam);
    std::copy(t, t + 3, cam + 9);
    cam[12] = fx, cam[13] = cx, cam[14] = fy, cam[15] = cy;
    const double tan_fovx = 0.5 * width / fx, tan_fovy = 0.5 * height / fy;
    cam[16] = (width - cx) / fx + 0.3 * tan_fovx, cam[17] = cx / fx + 0.3 * tan_fovx;
    cam[18] = (height - cy) / fy + 0.3 * tan_fovy, cam[19] = cy / fy + 0.3 * tan_fovy;
}

// one Gaussian's EWA terms in double (mean m [3], wxyz quaternion q [4], activated scales s [3]):
// out = [tz (camera depth), px, py (pixels, from the unclamped mean), aa, ab, bb (the rows A, B of
// J R_view R_q S: cov2d before eps2d = [[aa, ab], [ab, bb]]), axb2 = |A x B|^2]
template <typename S>
void terms(const double* cam, const S* m, const S* q, const S* s, double* out) {
    const double* R = cam;
    const double* t = cam + 9;
    const double fx = cam[12], cx = cam[13], fy = cam[14], cy = cam[15];
    const double mx = m[0], my = m[1], mz = m[2];
    const double tx = R[0] * mx + R[1] * my + R[2] * mz + t[0];
    const double ty = R[3] * mx + R[4] * my + R[5] * mz + t[1];
    const double tz = R[6] * mx + R[7] * my + R[8] * mz + t[2];
    const double rz = 1.0 / tz;
    out[0] = tz, out[1] = fx * tx * rz + cx, out[2] = fy * ty * rz + cy;
    const double u = std::min(std::max(tx * rz, -cam[17]), cam[16]);
    const double v = std::min(std::max(ty * rz, -cam[19]), cam[18]);
    const double a0 = fx * rz, a2 = -fx * u * rz, b1 = fy * rz, b2 = -fy * v * rz;
    const double J0[3] = {a0 * R[0] + a2 * R[6], a0 * R[1] + a2 * R[7], a0 * R[2] + a2 * R[8]};
    const double J1[3] = {b1 * R[3] + b2 * R[6], b1 * R[4] + b2 * R[7], b1 * R[5] + b2 * R[8]};
    // the rotation of the normalised wxyz quaternion (projection.quat_to_rotmat_rows)
    double qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    const double qn = std::max(std::sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12);
    qw /= qn, qx /= qn, qy /= qn, qz /= qn;
    const double Q[9] = {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy),
                         2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx),
                         2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)};
    double A[3], B[3];
    for (int c = 0; c < 3; ++c) {
        const double sc = s[c];
        A[c] = (J0[0] * Q[c] + J0[1] * Q[3 + c] + J0[2] * Q[6 + c]) * sc;
        B[c] = (J1[0] * Q[c] + J1[1] * Q[3 + c] + J1[2] * Q[6 + c]) * sc;
    }
    const double x0 = A[1] * B[2] - A[2] * B[1], x1 = A[2] * B[0] - A[0] * B[2], x2 = A[0] * B[1] - A[1] * B[0];
    out[3] = A[0] * A[0] + A[1] * A[1] + A[2] * A[2];
    out[4] = A[0] * B[0] + A[1] * B[1] + A[2] * B[2];
    out[5] = B[0] * B[0] + B[1] * B[1] + B[2] * B[2];
    out[6] = x0 * x0 + x1 * x1 + x2 * x2;
}

template void terms<float>(const double*, const float*, const float*, const float*, double*);
template void terms<double>(const double*, const double*, const double*, const double*, double*);

// gsplat's steps 4-6 for one Gaussian's terms (terms(): aa, ab, bb, axb2 and its pixel centre px,
// py): out = [c00, c01, c11 (cov2d + eps2d I), det (cancellation-free), rx, ry (ceil of the
// extent times the standard deviations, not capped)]; returns whether it is kept: det > 0 and
// finite, with an opacity (has_op) at least 1/255 (the extent then min(3.33, sqrt(2 log(255 op))),
// else 3.33), a radius above radius_clip and the box touching the image
bool footprint(double aa, double ab, double bb, double axb2, double px, double py, bool has_op, double op,
               double eps2d, double radius_clip, double width, double height, double* out) {
    out[0] = aa + eps2d, out[1] = ab, out[2] = bb + eps2d;
    out[3] = axb2 + eps2d * (aa + bb) + eps2d * eps2d;
    bool good = out[3] > 0 && std::isfinite(out[3]);  // an overflowing footprint is culled
    double extend = kExtend;
    if (has_op) {
        good = good && op >= kAlphaThreshold;
        extend = std::min(std::sqrt(2.0 * std::log(std::max(op, kAlphaThreshold) / kAlphaThreshold)), kExtend);
    }
    const double rx = std::ceil(extend * std::sqrt(out[0])), ry = std::ceil(extend * std::sqrt(out[2]));
    out[4] = rx, out[5] = ry;
    good = good && !(rx <= radius_clip && ry <= radius_clip);
    return good && !(px + rx <= 0 || px - rx >= width || py + ry <= 0 || py - ry >= height);
}

}  // namespace clod_ewa

namespace {

constexpr int64_t kGrain = 4096;  // ~50 ns an element
using clod_ewa::kMaxRadius;

template <typename S>
std::vector<torch::Tensor> geometry_impl(const torch::Tensor& means_t, const torch::Tensor& quats_t,
                                         const torch::Tensor& scales_t, const torch::Tensor& keep,
                                         const double* R, const double* t, double fx, double cx, double fy,
                                         double cy, double width, double height, double near_plane,
                                         double far_plane) {
    const S* means = means_t.data_ptr<S>();
    const S* quats = quats_t.data_ptr<S>();
    const S* scales = scales_t.data_ptr<S>();
    const bool all = keep.dim() == 0;  // a 0-dim keep: every row a candidate
    const int64_t n = all ? means_t.size(0) : keep.numel();
    const int64_t* kp = all ? nullptr : keep.data_ptr<int64_t>();
    std::vector<int64_t> ids;  // the rows in front of the camera, ascending as the candidates
    ids.reserve(n);
    for (int64_t j = 0; j < n; ++j) {
        const int64_t i = all ? j : kp[j];
        TORCH_CHECK(i >= 0 && i < means_t.size(0), "project_geometry: keep row ", i, " outside [0, ", means_t.size(0), ")");
        const double tz = R[6] * double(means[3 * i]) + R[7] * double(means[3 * i + 1]) +
                          R[8] * double(means[3 * i + 2]) + t[2];
        if (tz >= near_plane && tz <= far_plane) ids.push_back(i);
    }
    const int64_t m = static_cast<int64_t>(ids.size());
    auto opts = means_t.options();
    auto o_ids = torch::empty({m}, torch::TensorOptions().dtype(torch::kInt64));
    auto o_m2 = torch::empty({m, 2}, opts), o_z = torch::empty({m}, opts), o_aa = torch::empty({m}, opts),
         o_ab = torch::empty({m}, opts), o_bb = torch::empty({m}, opts), o_x = torch::empty({m}, opts);
    std::copy(ids.begin(), ids.end(), o_ids.data_ptr<int64_t>());
    S *m2 = o_m2.data_ptr<S>(), *zz = o_z.data_ptr<S>(), *aa = o_aa.data_ptr<S>(), *ab = o_ab.data_ptr<S>(),
      *bb = o_bb.data_ptr<S>(), *ax = o_x.data_ptr<S>();
    double cam[20];
    clod_ewa::camera(R, t, fx, cx, fy, cy, width, height, cam);
    at::parallel_for(0, m, kGrain, [&](int64_t b, int64_t e) {
        for (int64_t j = b; j < e; ++j) {
            const int64_t i = ids[j];
            double o[7];
            clod_ewa::terms<S>(cam, means + 3 * i, quats + 4 * i, scales + 3 * i, o);
            zz[j] = static_cast<S>(o[0]), m2[2 * j] = static_cast<S>(o[1]), m2[2 * j + 1] = static_cast<S>(o[2]);
            aa[j] = static_cast<S>(o[3]), ab[j] = static_cast<S>(o[4]), bb[j] = static_cast<S>(o[5]);
            ax[j] = static_cast<S>(o[6]);
        }
    });
    return {o_ids, o_m2, o_z, o_aa, o_ab, o_bb, o_x};
}

template <typename S>
std::vector<torch::Tensor> finish_impl(const torch::Tensor& m2_t, const torch::Tensor& aa_t,
                                       const torch::Tensor& ab_t, const torch::Tensor& bb_t,
                                       const torch::Tensor& ax_t, const torch::Tensor& op_t,
                                       const torch::Tensor& cs_t, double width, double height, double eps,
                                       double radius_clip) {
    const int64_t m = aa_t.numel();
    const S *m2 = m2_t.data_ptr<S>(), *aa = aa_t.data_ptr<S>(), *ab = ab_t.data_ptr<S>(), *bb = bb_t.data_ptr<S>(),
            *ax = ax_t.data_ptr<S>();
    const S* op = op_t.numel() ? op_t.data_ptr<S>() : nullptr;
    const S* cs = cs_t.numel() ? cs_t.data_ptr<S>() : nullptr;
    std::vector<double> fp(6 * m);  // per row: footprint()'s c00, c01, c11, det, rx, ry
    std::vector<char> ok(m);
    at::parallel_for(0, m, kGrain, [&](int64_t b, int64_t e) {
        for (int64_t j = b; j < e; ++j) {
            const double f = cs ? double(cs[j]) : 1.0;
            ok[j] = clod_ewa::footprint(aa[j] * f, ab[j] * f, bb[j] * f, ax[j] * (f * f), m2[2 * j], m2[2 * j + 1],
                                        op != nullptr, op ? double(op[j]) : 0.0, eps, radius_clip, width, height,
                                        fp.data() + 6 * j);
        }
    });
    std::vector<int64_t> sel;
    for (int64_t j = 0; j < m; ++j)
        if (ok[j]) sel.push_back(j);
    const int64_t v = static_cast<int64_t>(sel.size());
    auto o_sel = torch::empty({v}, torch::TensorOptions().dtype(torch::kInt64));
    auto o_rad = torch::empty({v, 2}, torch::TensorOptions().dtype(torch::kInt32));
    auto o_con = torch::empty({v, 3}, aa_t.options());
    std::copy(sel.begin(), sel.end(), o_sel.data_ptr<int64_t>());
    int32_t* rad = o_rad.data_ptr<int32_t>();
    S* con = o_con.data_ptr<S>();
    at::parallel_for(0, v, kGrain, [&](int64_t b, int64_t e) {
        for (int64_t k = b; k < e; ++k) {
            const double* q = fp.data() + 6 * sel[k];
            rad[2 * k] = static_cast<int32_t>(std::min(q[4], kMaxRadius));  // capped: a huge footprint cannot wrap
            rad[2 * k + 1] = static_cast<int32_t>(std::min(q[5], kMaxRadius));
            const double inv = 1.0 / q[3];
            con[3 * k] = static_cast<S>(q[2] * inv);
            con[3 * k + 1] = static_cast<S>(-q[1] * inv);
            con[3 * k + 2] = static_cast<S>(q[0] * inv);
        }
    });
    return {o_sel, o_rad, o_con};
}

void check_rows(const torch::Tensor& x, int64_t n, int64_t cols, const torch::Tensor& like, const char* what) {
    TORCH_CHECK(x.device().is_cpu() && x.is_contiguous() && x.scalar_type() == like.scalar_type() && x.size(0) == n &&
                    (cols == 0 ? x.dim() == 1 : (x.dim() == 2 && x.size(1) == cols)),
                what, ": contiguous CPU rows in the means' dtype");
}

}  // namespace

// clod_adapter.render.projection.project_geometry: means [N, 3], quats [N, 4] wxyz, activated scales
// [N, 3] (one float dtype); keep: [k] int64 candidate rows (ascending), or a 0-dim tensor for all N;
// R [9] row-major and t [3] of the world-to-camera matrix; intrinsics and image size in pixels.
// Returns [ids [M] int64, means2d [M, 2], depths [M], aa, ab, bb, axb2 [M]].
std::vector<torch::Tensor> project_geometry_cpu(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                                torch::Tensor keep, std::vector<double> R, std::vector<double> t,
                                                double fx, double cx, double fy, double cy, int64_t width,
                                                int64_t height, double near_plane, double far_plane) {
    TORCH_CHECK(R.size() == 9 && t.size() == 3, "project_geometry: R [9], t [3]");
    const int64_t n = means.size(0);
    check_rows(means, n, 3, means, "project_geometry means");
    check_rows(quats, n, 4, means, "project_geometry quats");
    check_rows(scales, n, 3, means, "project_geometry scales");
    TORCH_CHECK(keep.dim() == 0 || (keep.dim() == 1 && keep.scalar_type() == torch::kInt64 && keep.is_contiguous()),
                "project_geometry: keep is [k] int64 rows or a 0-dim tensor");
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_geometry", [&] {
        out = geometry_impl<scalar_t>(means, quats, scales, keep, R.data(), t.data(), fx, cx, fy, cy,
                                      static_cast<double>(width), static_cast<double>(height), near_plane, far_plane);
    });
    return out;
}

// clod_adapter.render.projection.finish_projection: a geometry's means2d [M, 2] and aa, ab, bb, axb2
// [M]; opacities [M] (or empty: extent 3.33, no opacity cull) and a covariance factor cov_scale [M]
// (or empty). Returns [rows [V] int64 (the kept rows, ascending), radii [V, 2] int32, conics [V, 3]].
std::vector<torch::Tensor> finish_projection_cpu(torch::Tensor means2d, torch::Tensor aa, torch::Tensor ab,
                                                 torch::Tensor bb, torch::Tensor axb2, torch::Tensor opacities,
                                                 torch::Tensor cov_scale, int64_t width, int64_t height, double eps2d,
                                                 double radius_clip) {
    const int64_t m = aa.numel();
    check_rows(means2d, m, 2, aa, "finish_projection means2d");
    for (const auto* x : {&aa, &ab, &bb, &axb2}) check_rows(*x, m, 0, aa, "finish_projection terms");
    if (opacities.numel()) check_rows(opacities, m, 0, aa, "finish_projection opacities");
    if (cov_scale.numel()) check_rows(cov_scale, m, 0, aa, "finish_projection cov_scale");
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(aa.scalar_type(), "finish_projection", [&] {
        out = finish_impl<scalar_t>(means2d, aa, ab, bb, axb2, opacities, cov_scale, static_cast<double>(width),
                                    static_cast<double>(height), eps2d, radius_clip);
    });
    return out;
}
