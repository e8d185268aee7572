// The merge tree's per-frame cut and its drawn attributes (docs/lod_rule.md steps 1-5): the cut
// walked from the roots, the attributes in one pass over the drawn rows.
//
// Twins: clod_adapter.lod.tree.walk, and terms + cut (tree_cut) and clod_adapter.lod.tree.cut_attributes
// (tree_attributes); tests/test_tree.py holds them together. As some 60 torch operations per
// frame, most over every node or every drawn row (gathers of the SH, interpolation of the rows
// in a hand-over, the concatenation of the tiers), the twins cost a fifth of a full-detail frame on
// 2 cores; here it is a loop per tier. Arithmetic in the centres' dtype, as the twins.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <tuple>
#include <type_traits>
#include <vector>

namespace clod_sh {
template <typename S>
void rgb(int degree, const S* coeffs, S dx, S dy, S dz, S* out);  // sh_colors.cpp
}  // namespace clod_sh

namespace {

constexpr int64_t kGrainCut = 16384;   // a log and a few divisions an element
constexpr int64_t kGrainRows = 2048;   // a row copies its SH (48 floats at degree 3)

template <typename S>
void cut_tier(int64_t n, const S* d_norm, const S* sigma_d, const S* exits, const int64_t* parent,
              const bool* lead, const S* E_up, S F, S Fk, bool first, bool last, S* E, S* U, bool* fade) {
    at::parallel_for(0, n, kGrainCut, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i) {
            const S d = std::max(d_norm[i], S(1e-12));
            S En = S(0);
            if (!first) {
                S v = sigma_d[i] / d;
                if (!last) v = std::min(v, E_up[parent[i]] / F);
                En = std::max(v, Fk);
            }
            E[i] = En;
            const S X = std::max(exits[i] / d, F * std::max(En, S(1)));
            if (last) {
                U[i] = X;
                fade[i] = true;
            } else {
                const S Ep = E_up[parent[i]];
                const bool f = !lead[i] && X < Ep;
                U[i] = f ? X : Ep;
                fade[i] = f;
            }
        }
    });
}

template <typename S>
void terms_impl(const std::vector<torch::Tensor>& d_norm, const std::vector<torch::Tensor>& sigma_d,
                const std::vector<torch::Tensor>& exits, const std::vector<torch::Tensor>& parents,
                const std::vector<torch::Tensor>& leads, double F,
                std::vector<torch::Tensor>& E, std::vector<torch::Tensor>& U, std::vector<torch::Tensor>& fade) {
    const int64_t T = static_cast<int64_t>(d_norm.size()) - 1;
    E.assign(T + 1, torch::Tensor());
    U.assign(T + 1, torch::Tensor());
    fade.assign(T + 1, torch::Tensor());
    for (int64_t k = T; k >= 0; --k) {
        const int64_t n = d_norm[k].size(0);
        auto opts = d_norm[k].options();
        E[k] = torch::empty({n}, opts);
        U[k] = torch::empty({n}, opts);
        fade[k] = torch::empty({n}, opts.dtype(torch::kBool));
        cut_tier<S>(n, d_norm[k].data_ptr<S>(), sigma_d[k].data_ptr<S>(), exits[k].data_ptr<S>(),
                    k < T ? parents[k].data_ptr<int64_t>() : nullptr, k < T ? leads[k].data_ptr<bool>() : nullptr,
                    k < T ? E[k + 1].data_ptr<S>() : nullptr, static_cast<S>(F),
                    static_cast<S>(std::pow(F, static_cast<double>(k))), k == 0, k == T, E[k].data_ptr<S>(),
                    U[k].data_ptr<S>(), fade[k].data_ptr<bool>());
    }
}

template <typename S>
void emit_cut(const std::vector<torch::Tensor>& E, const std::vector<torch::Tensor>& U,
              const std::vector<torch::Tensor>& fade, double s, double M, std::vector<torch::Tensor>& out) {
    const S Ms = static_cast<S>(M), sv = static_cast<S>(s);
    for (size_t k = 0; k < E.size(); ++k) {  // drawn iff E <= s < U; ids ascending (sequential: they are few or cheap)
        const int64_t n = E[k].size(0);
        const S* Ek = E[k].data_ptr<S>();
        const S* Uk = U[k].data_ptr<S>();
        const bool* fk = fade[k].data_ptr<bool>();
        std::vector<int64_t> ids;
        for (int64_t i = 0; i < n; ++i)
            if (Ek[i] <= sv && sv < Uk[i]) ids.push_back(i);
        const int64_t m = static_cast<int64_t>(ids.size());
        auto id_t = torch::empty({m}, torch::TensorOptions().dtype(torch::kInt64));
        auto w_t = torch::empty({m}, E[k].options());
        auto f_t = torch::empty({m}, torch::TensorOptions().dtype(torch::kBool));
        int64_t* ip = id_t.data_ptr<int64_t>();
        S* wp = w_t.data_ptr<S>();
        bool* fp = f_t.data_ptr<bool>();
        for (int64_t j = 0; j < m; ++j) {
            const int64_t i = ids[j];
            ip[j] = i;
            // w over the last min(M, U / max(E, 1)) of the node's interval (>= F: build keeps it so)
            const S width = std::min(Ms, Uk[i] / std::max(Ek[i], S(1)));
            wp[j] = std::min(std::max(std::log(Uk[i] / sv) / std::log(width), S(0)), S(1));
            fp[j] = fk[i];
        }
        out.push_back(id_t);
        out.push_back(w_t);
        out.push_back(f_t);
    }
}

// docs/lod_rule.md step 1's frustum test of one centre (world units; R [9] row-major, t [3]; pixels)
inline bool in_frustum(const double* R, const double* t, double fx, double cx, double fy, double cy, double width,
                       double height, double near_plane, double px, double py, double pz) {
    const double cz = R[6] * px + R[7] * py + R[8] * pz + t[2];
    const double cxs = R[0] * px + R[1] * py + R[2] * pz + t[0];
    const double cys = R[3] * px + R[4] * py + R[5] * pz + t[1];
    const double a = fx * cxs + cx * cz, bb = fy * cys + cy * cz;  // pixel * z
    return (cz > near_plane) & (a >= 0.0) & (a < cz * width) & (bb >= 0.0) & (bb < cz * height);
}

// D of docs/lod_rule.md step 1: the largest distance d of the last tier's n nodes in the frustum f
// (of all of them when none is), at least 1e-12; 1 for an empty tier
template <typename S, typename B>
S normaliser(const S* d, const B* f, int64_t n) {
    S D = S(0);
    bool any = false;
    for (int64_t i = 0; i < n; ++i)
        if (f[i]) D = any ? std::max(D, d[i]) : d[i], any = true;
    if (!any)
        for (int64_t i = 0; i < n; ++i) D = i ? std::max(D, d[i]) : d[i];
    return n == 0 ? S(1) : std::max(D, static_cast<S>(1e-12));
}

// The cut at one s_v walked from the roots (tree.walk's twin; docs/lod_rule.md: a renderer need
// not visit the children of a node that has entered): the roots' frustum and d' give D, then each
// tier below visits only the children of nodes not yet entered (s < E), in row order, so the ids
// come out ascending and a coarse frame does arithmetic for few nodes. A node not visited gets E =
// U = -inf: never drawn, its children never visited (a child's end is at most its parent's entry).
// Every visited node's terms are cut_tier's, rounded alike. Tier 0's frustum is counted over all
// its nodes (the population of a share of the view). Returns per tier [ids, w, fade], then the
// count as a 0-dim int64 tensor.
template <typename S>
std::vector<torch::Tensor> root_walk_impl(const std::vector<torch::Tensor>& cols, const double* R, const double* t,
                                         double fx, double cx, double fy, double cy, double width, double height,
                                         double near_plane, const double* c, const std::vector<torch::Tensor>& sigma_d,
                                         const std::vector<torch::Tensor>& exits,
                                         const std::vector<torch::Tensor>& parents,
                                         const std::vector<torch::Tensor>& leads, double s, double F, double M) {
    const int64_t T = static_cast<int64_t>(cols.size()) - 1;
    auto inside = [&](double px, double py, double pz) {
        return in_frustum(R, t, fx, cx, fy, cy, width, height, near_plane, px, py, pz);
    };
    auto dist = [&](const S* x, int64_t n, int64_t i) {  // in double, rounded to S (frame_impl)
        const double dx = double(x[i]) - c[0], dy = double(x[n + i]) - c[1], dz = double(x[2 * n + i]) - c[2];
        return static_cast<S>(std::sqrt(dx * dx + dy * dy + dz * dz));
    };
    // the roots: every one's d' (D is the largest distance of those in the frustum)
    const int64_t nT = cols[T].size(1);
    const S* xT = cols[T].data_ptr<S>();
    std::vector<S> dT(nT);
    std::vector<char> fT(nT);
    at::parallel_for(0, nT, kGrainCut, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i) fT[i] = inside(xT[i], xT[nT + i], xT[2 * nT + i]), dT[i] = dist(xT, nT, i);
    });
    const S D = normaliser(dT.data(), fT.data(), nT);
    for (int64_t i = 0; i < nT; ++i) dT[i] = dT[i] / D;
    const S Fs = static_cast<S>(F), sv = static_cast<S>(s), ninf = -std::numeric_limits<S>::infinity();
    std::vector<torch::Tensor> E(T + 1), U(T + 1), fade(T + 1);
    auto opts = cols[0].options();
    for (int64_t k = T; k >= 0; --k) {
        const int64_t n = cols[k].size(1);
        E[k] = torch::empty({n}, opts);
        U[k] = torch::empty({n}, opts);
        fade[k] = torch::empty({n}, opts.dtype(torch::kBool));
    }
    cut_tier<S>(nT, dT.data(), sigma_d[T].data_ptr<S>(), exits[T].data_ptr<S>(), nullptr, nullptr, nullptr, Fs,
                static_cast<S>(std::pow(F, static_cast<double>(T))), T == 0, true, E[T].data_ptr<S>(),
                U[T].data_ptr<S>(), fade[T].data_ptr<bool>());
    std::atomic<int64_t> n_frustum{0};
    if (T == 0)
        for (int64_t i = 0; i < nT; ++i) n_frustum += fT[i];
    for (int64_t k = T - 1; k >= 0; --k) {
        const int64_t n = cols[k].size(1);
        const S* x = cols[k].data_ptr<S>();
        const S *sg = sigma_d[k].data_ptr<S>(), *ex = exits[k].data_ptr<S>(), *Eup = E[k + 1].data_ptr<S>();
        const int64_t* par = parents[k].data_ptr<int64_t>();
        const bool* ld = leads[k].data_ptr<bool>();
        S *Ek = E[k].data_ptr<S>(), *Uk = U[k].data_ptr<S>();
        bool* fk = fade[k].data_ptr<bool>();
        const S Fk = static_cast<S>(std::pow(F, static_cast<double>(k)));
        at::parallel_for(0, n, kGrainCut, [&](int64_t b, int64_t e) {
            int64_t count = 0;
            for (int64_t i = b; i < e; ++i) {
                if (k == 0) count += inside(x[i], x[n + i], x[2 * n + i]);
                const S Ep = Eup[par[i]];
                if (!(sv < Ep)) {  // the parent was not visited or has entered: nothing below it is drawn
                    Ek[i] = Uk[i] = ninf;
                    fk[i] = false;
                    continue;
                }
                const S d = std::max(dist(x, n, i) / D, S(1e-12));
                const S En = k == 0 ? S(0) : std::max(std::min(sg[i] / d, Ep / Fs), Fk);  // cut_tier's
                const S X = std::max(ex[i] / d, Fs * std::max(En, S(1)));
                const bool f = !ld[i] && X < Ep;
                Ek[i] = En;
                Uk[i] = f ? X : Ep;
                fk[i] = f;
            }
            if (k == 0) n_frustum += count;
        });
    }
    std::vector<torch::Tensor> out;
    emit_cut<S>(E, U, fade, s, M, out);
    out.push_back(torch::full({}, n_frustum.load(), torch::TensorOptions().dtype(torch::kInt64)));
    return out;
}

template <typename S>
struct Tier {
    const S *means, *quats, *log_scales, *logits, *sh0, *shN;
    int64_t k_rest;  // SH coefficients in shN per channel
};

template <typename S>
Tier<S> tier_of(const std::vector<torch::Tensor>& attrs, int64_t k) {
    const auto& shN = attrs[6 * k + 5];
    return {attrs[6 * k].data_ptr<S>(), attrs[6 * k + 1].data_ptr<S>(), attrs[6 * k + 2].data_ptr<S>(),
            attrs[6 * k + 3].data_ptr<S>(), attrs[6 * k + 4].data_ptr<S>(), shN.data_ptr<S>(), shN.size(1)};
}

inline float sigmoid(float x) { return 1.0f / (1.0f + std::exp(-x)); }
inline double sigmoid(double x) { return 1.0 / (1.0 + std::exp(-x)); }

template <typename S>
std::vector<torch::Tensor> attributes_impl(const std::vector<torch::Tensor>& attrs, const std::vector<torch::Tensor>& ids,
                                           const std::vector<torch::Tensor>& ws, const std::vector<torch::Tensor>& fades,
                                           const std::vector<torch::Tensor>& parents,
                                           const std::vector<torch::Tensor>& leads, double shrink_floor,
                                           const std::vector<double>& campos, int64_t sh_degree) {
    const int64_t T = static_cast<int64_t>(ids.size()) - 1;
    int64_t M = 0;
    for (const auto& i : ids) M += i.numel();
    const int64_t KR = attrs[5].size(1), K = KR + 1;
    const bool rgb = !campos.empty();  // colours seen from campos instead of the SH coefficients
    TORCH_CHECK(!rgb || (campos.size() == 3 && K <= 16 && sh_degree >= 0 && (sh_degree + 1) * (sh_degree + 1) <= K),
                "tree_attributes: campos must hold 3 values and sh_degree fit the SH (at most degree 3)");
    const S cx = rgb ? static_cast<S>(campos[0]) : S(0), cy = rgb ? static_cast<S>(campos[1]) : S(0),
            cz = rgb ? static_cast<S>(campos[2]) : S(0);
    auto opts = attrs[0].options();
    auto o_means = torch::empty({M, 3}, opts), o_quats = torch::empty({M, 4}, opts),
         o_scales = torch::empty({M, 3}, opts), o_opac = torch::empty({M}, opts),
         o_col = rgb ? torch::empty({M, 3}, opts) : torch::empty({M, K, 3}, opts);
    S *om = o_means.data_ptr<S>(), *oq = o_quats.data_ptr<S>(), *os = o_scales.data_ptr<S>(),
      *oa = o_opac.data_ptr<S>(), *oc = o_col.data_ptr<S>();
    int64_t offset = 0;
    for (int64_t k = 0; k <= T; ++k) {
        const Tier<S> t = tier_of<S>(attrs, k);
        const bool has_parent = k < T;
        const Tier<S> p = has_parent ? tier_of<S>(attrs, k + 1) : t;
        const int64_t* id = ids[k].data_ptr<int64_t>();
        const S* w = ws[k].data_ptr<S>();
        const bool* fd = fades[k].data_ptr<bool>();
        const int64_t* par = has_parent ? parents[k].data_ptr<int64_t>() : nullptr;
        const bool* ld = has_parent ? leads[k].data_ptr<bool>() : nullptr;
        const int64_t m = ids[k].numel(), base = offset;
        at::parallel_for(0, m, kGrainRows, [&](int64_t b, int64_t e) {
            for (int64_t j = b; j < e; ++j) {
                const int64_t i = id[j], r = base + j;
                S mu[3], q[4], ls[3];
                for (int c = 0; c < 3; ++c) mu[c] = t.means[3 * i + c], ls[c] = t.log_scales[3 * i + c];
                for (int c = 0; c < 4; ++c) q[c] = t.quats[4 * i + c];
                S a = sigmoid(t.logits[i]);
                S row[48];
                S* col = rgb ? row : oc + r * K * 3;
                for (int c = 0; c < 3; ++c) col[c] = t.sh0[3 * i + c];
                const S* rest = t.shN + i * t.k_rest * 3;
                std::copy(rest, rest + t.k_rest * 3, col + 3);
                const S wj = w[j];
                if (fd[j]) {
                    a = a * wj;  // leaves: fades out
                } else if (has_parent && wj < S(1)) {
                    const int64_t pi = par[i];
                    if (ld[i]) {  // the lead grows into its parent
                        const S v = S(1) - wj;
                        for (int c = 0; c < 3; ++c) {
                            mu[c] = wj * mu[c] + v * p.means[3 * pi + c];
                            ls[c] = wj * ls[c] + v * p.log_scales[3 * pi + c];
                        }
                        S nq = 0, np = 0, dot = 0;
                        for (int c = 0; c < 4; ++c) nq += q[c] * q[c], np += p.quats[4 * pi + c] * p.quats[4 * pi + c];
                        nq = std::max(std::sqrt(nq), S(1e-12));
                        np = std::max(std::sqrt(np), S(1e-12));
                        S qp[4];
                        for (int c = 0; c < 4; ++c) q[c] = q[c] / nq, qp[c] = p.quats[4 * pi + c] / np, dot += q[c] * qp[c];
                        for (int c = 0; c < 4; ++c) q[c] = wj * q[c] + v * (dot < 0 ? -qp[c] : qp[c]);
                        for (int c = 0; c < 3; ++c) col[c] = wj * col[c] + v * p.sh0[3 * pi + c];
                        const S* prest = p.shN + pi * p.k_rest * 3;
                        for (int64_t c = 0; c < t.k_rest * 3; ++c) col[3 + c] = wj * col[3 + c] + v * prest[c];
                        a = wj * a + v * sigmoid(p.logits[pi]);
                    } else {  // a sibling shrinks and fades where it is
                        const S g = std::log(std::max(wj, static_cast<S>(shrink_floor)));
                        for (int c = 0; c < 3; ++c) ls[c] = ls[c] + g;
                        a = wj * a;
                    }
                }
                for (int c = 0; c < 3; ++c) om[3 * r + c] = mu[c], os[3 * r + c] = std::exp(ls[c]);
                for (int c = 0; c < 4; ++c) oq[4 * r + c] = q[c];
                oa[r] = a;
                if (rgb) clod_sh::rgb<S>(static_cast<int>(sh_degree), col, mu[0] - cx, mu[1] - cy, mu[2] - cz, oc + 3 * r);
            }
        });
        offset += m;
    }
    return {o_means, o_quats, o_scales, o_opac, o_col};
}

// the smallest position from which the summed weight of the intervals [lo, hi) holding it stays
// <= k (budget_s_v). The events are binned by the top bits of the position (positive floats order
// as their bits; 128 bins an octave for float, 16 for double): a bin whose start count plus all its
// entries stays <= k cannot break the bound, so only the last bin that may is sorted and scanned
// (and the one before it, should the bound prove loose). Exact: the same position as a full sort.
template <typename S>
struct BinKey;
template <>
struct BinKey<float> {
    using U = uint32_t;
    static constexpr int kShift = 16;
};
template <>
struct BinKey<double> {
    using U = uint64_t;
    static constexpr int kShift = 48;
};

template <typename S>
int64_t bin_of(S v, int64_t base) {
    typename BinKey<S>::U bits;
    std::memcpy(&bits, &v, sizeof(S));
    return static_cast<int64_t>(bits >> BinKey<S>::kShift) - base;
}

template <typename S>
double budget_impl(const std::vector<torch::Tensor>& E, const std::vector<torch::Tensor>& U,
                   const std::vector<torch::Tensor>& weights, double k) {
    const int64_t base = bin_of<S>(S(1), 0);
    const int64_t nbins = bin_of<S>(std::numeric_limits<S>::quiet_NaN(), base) + 2;  // up to inf and NaN
    std::vector<double> plus(nbins, 0.0), net(nbins, 0.0);
    std::vector<S> lowest(nbins, std::numeric_limits<S>::infinity());
    std::vector<char> used(nbins, 0);
    auto note = [&](S pos, double dw, int64_t b) {
        if (dw > 0) plus[b] += dw;
        net[b] += dw;
        used[b] = 1;
        lowest[b] = std::min(lowest[b], pos);
    };
    auto events = [&](auto&& visit) {  // every interval's two events: (position, weight change, bin)
        for (size_t t = 0; t < E.size(); ++t) {
            const S* e = E[t].data_ptr<S>();
            const S* u = U[t].data_ptr<S>();
            const double* w = weights[t].data_ptr<double>();
            const int64_t n = E[t].numel();
            for (int64_t i = 0; i < n; ++i) {
                const S lo = std::max(e[i], S(1));
                if (w[i] > 0 && u[i] > lo) {
                    visit(lo, w[i], bin_of<S>(lo, base));
                    visit(u[i], -w[i], std::min(bin_of<S>(u[i], base), nbins - 1));
                }
            }
        }
    };
    note(S(1), 0.0, bin_of<S>(S(1), base));
    events(note);
    std::vector<double> start(nbins + 1, 0.0);  // summed weight drawn before each bin's first position
    for (int64_t b = 0; b < nbins; ++b) start[b + 1] = start[b] + net[b];
    const double limit = k + 1e-9 * std::abs(k);  // summed in another order than k was
    bool have = false;  // the smallest position seen so far from which the bound holds
    S answer = S(1);
    for (int64_t b = nbins - 1; b >= 0; --b) {
        if (!used[b]) continue;
        if (start[b] + plus[b] <= limit) {  // no position of this bin can exceed k
            answer = lowest[b], have = true;
            continue;
        }
        std::vector<std::pair<S, double>> ev;  // this bin's events, sorted
        events([&](S pos, double dw, int64_t bin) {
            if (bin == b) ev.emplace_back(pos, dw);
        });
        if (bin_of<S>(S(1), base) == b) ev.emplace_back(S(1), 0.0);
        std::sort(ev.begin(), ev.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
        std::vector<S> uniq;
        std::vector<double> count;  // summed weight drawn on [uniq[j], uniq[j + 1])
        double run = start[b];
        for (const auto& [pos, dw] : ev) {
            if (uniq.empty() || pos != uniq.back()) {
                if (!uniq.empty()) count.push_back(run);
                uniq.push_back(pos);
            }
            run += dw;
        }
        count.push_back(run);
        for (int64_t j = static_cast<int64_t>(uniq.size()) - 1; j >= 0; --j) {
            if (count[j] > limit) {  // the bound breaks here: it holds from the next position on
                if (j + 1 < static_cast<int64_t>(uniq.size())) return static_cast<double>(uniq[j + 1]);
                return static_cast<double>(have ? answer : uniq[j]);
            }
            answer = uniq[j], have = true;
        }
    }
    return static_cast<double>(answer);
}

// A count budget's level by walking the intervals' ends from the coarsest down (budget_s_v with
// weights 0 or 1, the frustum): the ends are the camera-independent terms at the reference
// distances, sorted once per model (budget_events), so a frame visits only the ends above the
// level it finds, few for a small budget. count(q) = the nodes in the frustum with lo <= q < hi,
// lo = max(E, 1), hi = U; the level is the smallest candidate q (an end of a node in the frustum,
// or 1) from which every candidate's count is at most k (the coarsest such end where none holds).
template <typename S>
std::vector<torch::Tensor> events_impl(const std::vector<torch::Tensor>& E, const std::vector<torch::Tensor>& U) {
    std::vector<std::tuple<S, int64_t, bool>> ev;  // (position, tier << 48 | row, the interval's end)
    for (size_t t = 0; t < E.size(); ++t) {
        const S* e = E[t].data_ptr<S>();
        const S* u = U[t].data_ptr<S>();
        for (int64_t i = 0; i < E[t].numel(); ++i) {
            const S lo = std::max(e[i], S(1));
            if (u[i] > lo) {
                const int64_t node = (static_cast<int64_t>(t) << 48) | i;
                ev.emplace_back(lo, node, false);
                ev.emplace_back(u[i], node, true);
            }
        }
    }
    std::sort(ev.begin(), ev.end(), [](const auto& a, const auto& b) { return std::get<0>(a) > std::get<0>(b); });
    const int64_t n = static_cast<int64_t>(ev.size());
    auto pos = torch::empty({n}, E[0].options());
    auto node = torch::empty({n}, torch::TensorOptions().dtype(torch::kInt64));
    auto hi = torch::empty({n}, torch::TensorOptions().dtype(torch::kBool));
    S* pp = pos.data_ptr<S>();
    int64_t* np = node.data_ptr<int64_t>();
    bool* hp = hi.data_ptr<bool>();
    for (int64_t j = 0; j < n; ++j) pp[j] = std::get<0>(ev[j]), np[j] = std::get<1>(ev[j]), hp[j] = std::get<2>(ev[j]);
    return {pos, node, hi};
}

template <typename S>
double walk_impl(const torch::Tensor& pos, const torch::Tensor& node, const torch::Tensor& hi,
                 const std::vector<torch::Tensor>& frustum, double k) {
    const S* pp = pos.data_ptr<S>();
    const int64_t* np = node.data_ptr<int64_t>();
    const bool* hp = hi.data_ptr<bool>();
    std::vector<const bool*> fr;
    for (const auto& f : frustum) fr.push_back(f.data_ptr<bool>());
    const double limit = k + 1e-9 * std::abs(k);  // as budget_impl
    const int64_t n = pos.numel();
    const int64_t mask = (int64_t(1) << 48) - 1;
    double run = 0.0;  // count just below the last candidate evaluated (every end above applied)
    bool have = false;
    S ok = S(1);  // the lowest candidate so far whose count, and every higher one's, is <= k
    for (int64_t i = 0; i < n;) {
        const S q = pp[i];
        double delta = 0.0;
        bool any = false;
        for (; i < n && pp[i] == q; ++i) {
            if (!fr[np[i] >> 48][np[i] & mask]) continue;
            any = true;
            delta += hp[i] ? 1.0 : -1.0;  // below an end the node is drawn; below its entry, not
        }
        if (!any) continue;
        if (run > limit) return static_cast<double>(have ? ok : q);
        ok = q, have = true;
        run += delta;
        if (q == S(1)) return 1.0;
    }
    if (run > limit) return static_cast<double>(have ? ok : S(1));
    return 1.0;
}

// tree_frame: per tier the frustum test and d' of every node (docs/lod_rule.md step 1): the
// distance to the camera in double, rounded to S, over D = the largest of the last tier's in the
// frustum (of all of them when none is), divided in S (tree._frame_twin rounds alike). Without a
// camera centre (c == nullptr: a budget's frame, whose d' are the stored ones) the frustum alone.
template <typename S>
std::vector<torch::Tensor> frame_impl(const std::vector<torch::Tensor>& cols, const double* R, const double* t,
                                      double fx, double cx, double fy, double cy, double width, double height,
                                      double near_plane, const double* c) {
    const size_t T = cols.size();
    std::vector<torch::Tensor> fr(T), d(T);
    for (size_t k = 0; k < T; ++k) {
        const int64_t n = cols[k].size(1);
        fr[k] = torch::empty({n}, cols[k].options().dtype(torch::kBool));
        if (c) d[k] = torch::empty({n}, cols[k].options());
        const S* x = cols[k].data_ptr<S>();
        const S *y = x + n, *z = x + 2 * n;
        bool* f = fr[k].data_ptr<bool>();
        S* dd = c ? d[k].data_ptr<S>() : nullptr;
        at::parallel_for(0, n, kGrainCut, [&](int64_t b, int64_t e) {
            for (int64_t i = b; i < e; ++i) {
                f[i] = in_frustum(R, t, fx, cx, fy, cy, width, height, near_plane, x[i], y[i], z[i]);
            }
            if (dd)
                for (int64_t i = b; i < e; ++i) {
                    const double dx = double(x[i]) - c[0], dy = double(y[i]) - c[1], dz = double(z[i]) - c[2];
                    dd[i] = static_cast<S>(std::sqrt(dx * dx + dy * dy + dz * dz));
                }
        });
    }
    if (!c) return fr;
    const int64_t nT = cols[T - 1].size(1);
    const bool* fT = fr[T - 1].data_ptr<bool>();
    const S* dT = d[T - 1].data_ptr<S>();
    const S D = normaliser(dT, fT, nT);
    std::vector<torch::Tensor> out;
    for (size_t k = 0; k < T; ++k) {
        S* dd = d[k].data_ptr<S>();
        const int64_t n = d[k].numel();
        for (int64_t i = 0; i < n; ++i) dd[i] = dd[i] / D;
        out.push_back(fr[k]);
        out.push_back(d[k]);
    }
    return out;
}

}  // namespace

// clod_adapter.lod.tree.frame: cols per tier [3, N_k] contiguous (lod.centre_columns, one dtype); R [9]
// row-major and t [3] of the world-to-camera matrix; intrinsics and image size in pixels; the camera
// centre (world). Returns per tier [frustum [N_k] bool, d' [N_k]]; with an empty centre, per tier
// the frustum [N_k] bool alone (tree.budget_frame).
std::vector<torch::Tensor> tree_frame_cpu(std::vector<torch::Tensor> cols, std::vector<double> R, std::vector<double> t,
                                          double fx, double cx, double fy, double cy, int64_t width, int64_t height,
                                          double near_plane, std::vector<double> center) {
    TORCH_CHECK(!cols.empty() && R.size() == 9 && t.size() == 3 && (center.size() == 3 || center.empty()),
                "tree_frame: tiers, R [9], t [3], c [3] or none");
    for (const auto& c : cols)
        TORCH_CHECK(c.dim() == 2 && c.size(0) == 3 && c.is_contiguous() && c.device().is_cpu() &&
                    c.scalar_type() == cols[0].scalar_type(), "tree_frame: contiguous CPU [3, N] columns of one dtype");
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(cols[0].scalar_type(), "tree_frame", [&] {
        out = frame_impl<scalar_t>(cols, R.data(), t.data(), fx, cx, fy, cy, static_cast<double>(width),
                                   static_cast<double>(height), near_plane,
                                   center.empty() ? nullptr : center.data());
    });
    return out;
}

// clod_adapter.lod.tree.budget_s_v: per tier E, U [N_k] and weights [N_k] float64
double tree_budget_cpu(std::vector<torch::Tensor> E, std::vector<torch::Tensor> U,
                       std::vector<torch::Tensor> weights, double k) {
    TORCH_CHECK(!E.empty() && U.size() == E.size() && weights.size() == E.size(), "tree_budget: one entry per tier");
    double out = 0.0;
    AT_DISPATCH_FLOATING_TYPES(E[0].scalar_type(), "tree_budget", [&] {
        out = budget_impl<scalar_t>(E, U, weights, k);
    });
    return out;
}

// clod_adapter.lod.tree.cut at one s_v, walked from the roots (root_walk_impl): cols per tier [3, N_k]
// contiguous (lod.centre_columns) and the camera as tree_frame takes it, the centre c [3]; the nodes'
// constants per tier. Returns per tier [ids (int64, ascending), w, fade], then tier 0's frustum count.
std::vector<torch::Tensor> tree_cut_cpu(std::vector<torch::Tensor> cols, std::vector<double> R, std::vector<double> t,
                                        double fx, double cx, double fy, double cy, int64_t width, int64_t height,
                                        double near_plane, std::vector<double> center, std::vector<torch::Tensor> sigma_d,
                                        std::vector<torch::Tensor> exits, std::vector<torch::Tensor> parents,
                                        std::vector<torch::Tensor> leads, double s, double F, double M) {
    TORCH_CHECK(!cols.empty() && sigma_d.size() == cols.size() && exits.size() == cols.size() &&
                parents.size() + 1 == cols.size() && leads.size() + 1 == cols.size(), "tree_cut: one entry per tier");
    TORCH_CHECK(R.size() == 9 && t.size() == 3 && center.size() == 3, "tree_cut: R [9], t [3], c [3]");
    for (size_t k = 0; k < cols.size(); ++k) {
        TORCH_CHECK(cols[k].dim() == 2 && cols[k].size(0) == 3 && cols[k].is_contiguous() && cols[k].device().is_cpu() &&
                    cols[k].scalar_type() == cols[0].scalar_type(), "tree_cut: contiguous CPU [3, N] columns of one dtype");
        TORCH_CHECK(sigma_d[k].numel() == cols[k].size(1) && exits[k].numel() == cols[k].size(1) &&
                    sigma_d[k].scalar_type() == cols[0].scalar_type() && exits[k].scalar_type() == cols[0].scalar_type() &&
                    sigma_d[k].is_contiguous() && exits[k].is_contiguous(), "tree_cut: [N_k] sigma_d and exits in the centres' dtype");
        if (k + 1 < cols.size())
            TORCH_CHECK(parents[k].numel() == cols[k].size(1) && leads[k].numel() == cols[k].size(1) &&
                        parents[k].scalar_type() == torch::kInt64 && leads[k].scalar_type() == torch::kBool &&
                        parents[k].is_contiguous() && leads[k].is_contiguous(), "tree_cut: [N_k] int64 parents and bool leads");
    }
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(cols[0].scalar_type(), "tree_cut", [&] {
        out = root_walk_impl<scalar_t>(cols, R.data(), t.data(), fx, cx, fy, cy, static_cast<double>(width),
                                      static_cast<double>(height), near_plane, center.data(), sigma_d, exits, parents,
                                      leads, s, F, M);
    });
    return out;
}

// clod_adapter.lod.tree.terms: per tier [E, U, fade] of every node
std::vector<torch::Tensor> tree_terms_cpu(std::vector<torch::Tensor> d_norm, std::vector<torch::Tensor> sigma_d,
                                          std::vector<torch::Tensor> exits, std::vector<torch::Tensor> parents,
                                          std::vector<torch::Tensor> leads, double F) {
    TORCH_CHECK(!d_norm.empty() && sigma_d.size() == d_norm.size() && exits.size() == d_norm.size() &&
                parents.size() + 1 == d_norm.size() && leads.size() + 1 == d_norm.size(), "tree_terms: one entry per tier");
    std::vector<torch::Tensor> E, U, fade, out;
    AT_DISPATCH_FLOATING_TYPES(d_norm[0].scalar_type(), "tree_terms", [&] {
        terms_impl<scalar_t>(d_norm, sigma_d, exits, parents, leads, F, E, U, fade);
    });
    for (size_t k = 0; k < E.size(); ++k) {
        out.push_back(E[k]);
        out.push_back(U[k]);
        out.push_back(fade[k]);
    }
    return out;
}

// the sorted ends of a budget's intervals (walk_impl): (positions descending, tier << 48 | row,
// whether the position is the node's end U rather than its entry max(E, 1))
std::vector<torch::Tensor> tree_budget_events_cpu(std::vector<torch::Tensor> E, std::vector<torch::Tensor> U) {
    TORCH_CHECK(!E.empty() && U.size() == E.size(), "tree_budget_events: one entry per tier");
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(E[0].scalar_type(), "tree_budget_events", [&] { out = events_impl<scalar_t>(E, U); });
    return out;
}

// a count budget's level and cut from the cached terms and ends: per tier [ids, w, fade], then a
// 0-dim float64 tensor of the level
std::vector<torch::Tensor> tree_budget_walk_cpu(std::vector<torch::Tensor> E, std::vector<torch::Tensor> U,
                                                std::vector<torch::Tensor> fade, torch::Tensor pos, torch::Tensor node,
                                                torch::Tensor hi, std::vector<torch::Tensor> frustum, double k, double M) {
    TORCH_CHECK(!E.empty() && U.size() == E.size() && fade.size() == E.size() && frustum.size() == E.size(),
                "tree_budget_walk: one entry per tier");
    for (const auto& f : frustum) TORCH_CHECK(f.scalar_type() == torch::kBool && f.is_contiguous(), "tree_budget_walk: bool frustum masks");
    std::vector<torch::Tensor> out;
    double level = 1.0;
    AT_DISPATCH_FLOATING_TYPES(E[0].scalar_type(), "tree_budget_walk", [&] {
        level = walk_impl<scalar_t>(pos, node, hi, frustum, k);
        emit_cut<scalar_t>(E, U, fade, std::max(level, 1.0), M, out);
    });
    out.push_back(torch::full({}, level, torch::TensorOptions().dtype(torch::kFloat64)));
    return out;
}

// clod_adapter.lod.tree.cut_attributes: attrs per tier (means, quats, log_scales, opacity_logits, sh0, shN),
// the cut's ids / w / fade per tier; returns (means, quats, scales, opacities, colors [M, K, 3])
std::vector<torch::Tensor> tree_attributes_cpu(std::vector<torch::Tensor> attrs, std::vector<torch::Tensor> ids,
                                               std::vector<torch::Tensor> ws, std::vector<torch::Tensor> fades,
                                               std::vector<torch::Tensor> parents, std::vector<torch::Tensor> leads,
                                               double shrink_floor, std::vector<double> campos, int64_t sh_degree) {
    TORCH_CHECK(attrs.size() == 6 * ids.size() && ws.size() == ids.size() && fades.size() == ids.size() &&
                parents.size() + 1 == ids.size() && leads.size() + 1 == ids.size(), "tree_attributes: one entry per tier");
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(attrs[0].scalar_type(), "tree_attributes", [&] {
        out = attributes_impl<scalar_t>(attrs, ids, ws, fades, parents, leads, shrink_floor, campos, sh_degree);
    });
    return out;
}
