// The merge tree's per-frame cut and its drawn attributes (docs/lod_rule.md steps 1-5) in one
// pass over the nodes each.
//
// Twins: clod_adapter.tree.terms + cut (tree_cut) and clod_adapter.tree.cut_attributes
// (tree_attributes); tests/test_tree.py holds them together. As some 60 torch operations per
// frame, most over every node or every drawn row (gathers of the SH, interpolation of the rows
// in a hand-over, the concatenation of the tiers), the twins cost a fifth of a full-detail frame on
// 2 cores; here it is a loop per tier. Arithmetic in the centres' dtype, as the twins.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

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
std::vector<torch::Tensor> cut_impl(const std::vector<torch::Tensor>& d_norm, const std::vector<torch::Tensor>& sigma_d,
                                    const std::vector<torch::Tensor>& exits, const std::vector<torch::Tensor>& parents,
                                    const std::vector<torch::Tensor>& leads, double s, double F) {
    const int64_t T = static_cast<int64_t>(d_norm.size()) - 1;
    const S lnF = std::log(static_cast<S>(F)), sv = static_cast<S>(s);
    std::vector<torch::Tensor> E, U, fade;
    terms_impl<S>(d_norm, sigma_d, exits, parents, leads, F, E, U, fade);
    std::vector<torch::Tensor> out;
    for (int64_t k = 0; k <= T; ++k) {  // drawn iff E <= s < U; ids ascending (sequential: they are few or cheap)
        const int64_t n = d_norm[k].size(0);
        const S* Ek = E[k].data_ptr<S>();
        const S* Uk = U[k].data_ptr<S>();
        const bool* fk = fade[k].data_ptr<bool>();
        std::vector<int64_t> ids;
        for (int64_t i = 0; i < n; ++i)
            if (Ek[i] <= sv && sv < Uk[i]) ids.push_back(i);
        const int64_t m = static_cast<int64_t>(ids.size());
        auto id_t = torch::empty({m}, torch::TensorOptions().dtype(torch::kInt64));
        auto w_t = torch::empty({m}, d_norm[k].options());
        auto f_t = torch::empty({m}, torch::TensorOptions().dtype(torch::kBool));
        int64_t* ip = id_t.data_ptr<int64_t>();
        S* wp = w_t.data_ptr<S>();
        bool* fp = f_t.data_ptr<bool>();
        for (int64_t j = 0; j < m; ++j) {
            const int64_t i = ids[j];
            ip[j] = i;
            wp[j] = std::min(std::max(std::log(Uk[i] / sv) / lnF, S(0)), S(1));
            fp[j] = fk[i];
        }
        out.push_back(id_t);
        out.push_back(w_t);
        out.push_back(f_t);
    }
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
                                           const std::vector<torch::Tensor>& leads, double shrink_floor) {
    const int64_t T = static_cast<int64_t>(ids.size()) - 1;
    int64_t M = 0;
    for (const auto& i : ids) M += i.numel();
    const int64_t KR = attrs[5].size(1), K = KR + 1;
    auto opts = attrs[0].options();
    auto o_means = torch::empty({M, 3}, opts), o_quats = torch::empty({M, 4}, opts),
         o_scales = torch::empty({M, 3}, opts), o_opac = torch::empty({M}, opts), o_col = torch::empty({M, K, 3}, opts);
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
                S* col = oc + r * K * 3;
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
            }
        });
        offset += m;
    }
    return {o_means, o_quats, o_scales, o_opac, o_col};
}

// the smallest position from which the summed weight of the intervals [lo, hi) holding it stays
// <= k (budget_s_v); events sorted by position with an LSD radix sort on the float's bits (positive
// floats order as their bits), three passes of 11 bits
template <typename S>
double budget_impl(const std::vector<torch::Tensor>& E, const std::vector<torch::Tensor>& U,
                   const std::vector<torch::Tensor>& weights, double k) {
    size_t total = 1;
    for (const auto& e : E) total += 2 * static_cast<size_t>(e.numel());
    std::vector<S> pos;
    std::vector<double> delta;
    pos.reserve(total);
    delta.reserve(total);
    for (size_t t = 0; t < E.size(); ++t) {
        const S* e = E[t].data_ptr<S>();
        const S* u = U[t].data_ptr<S>();
        const double* w = weights[t].data_ptr<double>();
        const int64_t n = E[t].numel();
        for (int64_t i = 0; i < n; ++i) {
            const S lo = std::max(e[i], S(1));
            if (w[i] > 0 && u[i] > lo) {
                pos.push_back(lo), delta.push_back(w[i]);
                pos.push_back(u[i]), delta.push_back(-w[i]);
            }
        }
    }
    pos.push_back(S(1)), delta.push_back(0.0);
    const size_t m = pos.size();
    std::vector<uint32_t> order(m), tmp(m);
    for (size_t i = 0; i < m; ++i) order[i] = static_cast<uint32_t>(i);
    if constexpr (std::is_same_v<S, float>) {
        std::vector<uint32_t> key(m), key_tmp(m);
        std::memcpy(key.data(), pos.data(), m * sizeof(uint32_t));
        for (int shift = 0; shift < 32; shift += 11) {  // keys and rows moved together: sequential reads
            std::vector<size_t> count(2049, 0);
            for (size_t i = 0; i < m; ++i) ++count[((key[i] >> shift) & 2047u) + 1];
            for (size_t b = 1; b < count.size(); ++b) count[b] += count[b - 1];
            for (size_t i = 0; i < m; ++i) {
                const size_t to = count[(key[i] >> shift) & 2047u]++;
                key_tmp[to] = key[i];
                tmp[to] = order[i];
            }
            key.swap(key_tmp);
            order.swap(tmp);
        }
    } else {
        std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return pos[a] < pos[b]; });
    }
    std::vector<S> uniq;
    std::vector<double> count;  // summed weight drawn on [uniq[j], uniq[j + 1])
    double run = 0.0;
    for (size_t j = 0; j < m; ++j) {
        const size_t i = order[j];
        if (uniq.empty() || pos[i] != uniq.back()) {
            if (!uniq.empty()) count.push_back(run);
            uniq.push_back(pos[i]);
        }
        run += delta[i];
    }
    count.push_back(run);
    const double limit = k + 1e-9 * std::abs(k);  // summed in another order than k was
    int64_t first = -1;
    double suffix = -std::numeric_limits<double>::infinity();
    for (int64_t j = static_cast<int64_t>(uniq.size()) - 1; j >= 0; --j) {
        suffix = std::max(suffix, count[j]);
        if (suffix <= limit) first = j;
        else break;
    }
    return static_cast<double>(first >= 0 ? uniq[first] : uniq.back());
}

}  // namespace

// clod_adapter.tree.budget_s_v: per tier E, U [N_k] and weights [N_k] float64
double tree_budget_cpu(std::vector<torch::Tensor> E, std::vector<torch::Tensor> U,
                       std::vector<torch::Tensor> weights, double k) {
    TORCH_CHECK(!E.empty() && U.size() == E.size() && weights.size() == E.size(), "tree_budget: one entry per tier");
    double out = 0.0;
    AT_DISPATCH_FLOATING_TYPES(E[0].scalar_type(), "tree_budget", [&] {
        out = budget_impl<scalar_t>(E, U, weights, k);
    });
    return out;
}

// clod_adapter.tree.cut at one s_v from every node's terms (d_norm: per tier [N_k] its d', as
// tree._distances rounds it): per tier [ids (int64, ascending), w, fade]
std::vector<torch::Tensor> tree_cut_cpu(std::vector<torch::Tensor> d_norm, std::vector<torch::Tensor> sigma_d,
                                        std::vector<torch::Tensor> exits, std::vector<torch::Tensor> parents,
                                        std::vector<torch::Tensor> leads, double s, double F) {
    TORCH_CHECK(!d_norm.empty() && sigma_d.size() == d_norm.size() && exits.size() == d_norm.size() &&
                parents.size() + 1 == d_norm.size() && leads.size() + 1 == d_norm.size(), "tree_cut: one entry per tier");
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(d_norm[0].scalar_type(), "tree_cut", [&] {
        out = cut_impl<scalar_t>(d_norm, sigma_d, exits, parents, leads, s, F);
    });
    return out;
}

// clod_adapter.tree.terms: per tier [E, U, fade] of every node
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

// clod_adapter.tree.cut_attributes: attrs per tier (means, quats, log_scales, opacity_logits, sh0, shN),
// the cut's ids / w / fade per tier; returns (means, quats, scales, opacities, colors [M, K, 3])
std::vector<torch::Tensor> tree_attributes_cpu(std::vector<torch::Tensor> attrs, std::vector<torch::Tensor> ids,
                                               std::vector<torch::Tensor> ws, std::vector<torch::Tensor> fades,
                                               std::vector<torch::Tensor> parents, std::vector<torch::Tensor> leads,
                                               double shrink_floor) {
    TORCH_CHECK(attrs.size() == 6 * ids.size() && ws.size() == ids.size() && fades.size() == ids.size() &&
                parents.size() + 1 == ids.size() && leads.size() + 1 == ids.size(), "tree_attributes: one entry per tier");
    std::vector<torch::Tensor> out;
    AT_DISPATCH_FLOATING_TYPES(attrs[0].scalar_type(), "tree_attributes", [&] {
        out = attributes_impl<scalar_t>(attrs, ids, ws, fades, parents, leads, shrink_floor);
    });
    return out;
}
