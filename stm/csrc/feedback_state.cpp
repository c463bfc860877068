// What a self-fed step feeds back: see feedback_state.h. (Edit this file with the header: the build is keyed
// on the sources only.)
#include "feedback_state.h"

#include <ATen/Dispatch.h>

#include <algorithm>
#include <cmath>

#include "rows.h"
#include "vec_math.h"

namespace stm_cpp {
namespace {

// ATen's clamp: NaN stays NaN (std::max(NaN, lo) is NaN, and so is std::min of it).
template <typename T>
T clamp(T v, T lo, T hi) {
  return std::min(std::max(v, lo), hi);
}

template <typename T>
void joints_row(const T* qp, const T* pr, const T* lo, const T* hi, const T* mean, T* q, bool* mq, T* x, bool* mg) {
  for (int64_t i = 0; i < JOINTS; ++i) {
    const T z = qp[i] + pr[i];
    q[i] = clamp(z, lo[i], hi[i]);
    mq[i] = z >= lo[i] && z <= hi[i];
    x[i] = (q[i] - qp[i]) - mean[i];
  }
  if (mg != nullptr) {
    const T g_raw = pr[JOINTS], g = clamp(g_raw, T(0), T(1));
    *mg = g_raw >= T(0) && g_raw <= T(1);
    x[JOINTS] = (g + (std::nearbyint(g) - g)) - mean[JOINTS];  // round half to even, as torch.round
  }
}

// One row's backward (see fed_backward); dpred: the prediction's gradient columns, scattered by the caller.
template <typename T>
void backward_row(const T* dx, const T* gq, const T* jac, const bool* mq, const bool* mg, int64_t phi_start,
                  int64_t phi_dim, T* gq_new, T* dpred) {
  for (int64_t i = 0; i < JOINTS; ++i) {
    T dq = gq != nullptr ? gq[i] + dx[i] : dx[i];
    if (jac != nullptr) {
      const T* d_tip = dx + phi_start;
      const T* row = jac + 3 * i;
      dq = dq + ((row[0] * d_tip[0] + row[1] * d_tip[1]) + row[2] * d_tip[2]);
    }
    const T dz = mq[i] ? dq : T(0);
    gq_new[i] = dz - dx[i];
    dpred[i] = dz;
  }
  if (mg != nullptr) dpred[JOINTS] = *mg ? dx[JOINTS] : T(0);
  for (int64_t c = 0; c < phi_dim; ++c) dpred[phi_start + c] = dx[phi_start + c];
}

}  // namespace

void fed_joints(const Block& q_prev, const Block& pred, const Block& lower, const Block& upper, const Block& mean,
                const Block& q, const Block& mask_q, const Block& x, const Block& mask_g, int64_t K, int64_t B) {
  const auto mq = rows<bool>(mask_q), mg = rows<bool>(mask_g);
  AT_DISPATCH_FLOATING_TYPES(pred.dtype, "fed_joints", [&] {
    using T = scalar_t;
    const auto qp = rows<T>(q_prev), pr = rows<T>(pred), lo = rows<T>(lower), hi = rows<T>(upper),
               mu = rows<T>(mean), qr = rows<T>(q), xr = rows<T>(x);
    for (int64_t k = 0; k < K; ++k) {
      for (int64_t b = 0; b < B; ++b) {
        joints_row<T>(qp.at(k, b), pr.at(k, b), lo.at(k, b), hi.at(k, b), mu.at(k, b), qr.at(k, b), mq.at(k, b),
                      xr.at(k, b), mg.p != nullptr ? mg.at(k, b) : nullptr);
      }
    }
  });
}

void fed_context(const Block& phi_src, int64_t phi_dim, const Block& offset, const Block& psi, int64_t psi_dim,
                 const Block& mean, int64_t phi_start, const Block& x, int64_t K, int64_t B) {
  const int64_t P = psi_dim;
  AT_DISPATCH_FLOATING_TYPES(phi_src.dtype, "fed_context", [&] {
    using T = scalar_t;
    const auto src = rows<T>(phi_src), off = rows<T>(offset), ps = rows<T>(psi), mu = rows<T>(mean),
               xr = rows<T>(x);
    for (int64_t k = 0; k < K; ++k) {
      for (int64_t b = 0; b < B; ++b) {
        const T* s = src.at(k, b);
        const T* m = mu.at(k, b) + phi_start;
        T* xp = xr.at(k, b) + phi_start;
        for (int64_t c = 0; c < phi_dim; ++c) xp[c] = (off.p != nullptr ? s[c] + off.at(k, b)[c] : s[c]) - m[c];
        for (int64_t c = 0; c < P; ++c) xp[phi_dim + c] = ps.at(k, b)[c] - m[phi_dim + c];
      }
    }
  });
}

void fed_backward(const Block& dx, const Block& gq, const Block& jac, const Block& mask_q, const Block& mask_g,
                  const Block& idx, int64_t phi_start, int64_t phi_dim, int64_t mixtures, int64_t dims,
                  const Block& gq_new, const Block& dout, int64_t K, int64_t B, at::ScalarType dtype) {
  const auto mq = rows<bool>(mask_q), mg = rows<bool>(mask_g);
  const auto ix = rows<int64_t>(idx);
  AT_DISPATCH_FLOATING_TYPES(dtype, "fed_backward", [&] {
    using T = scalar_t;
    const auto d = rows<T>(dx), g = rows<T>(gq), jr = rows<T>(jac), gn = rows<T>(gq_new), out = rows<T>(dout);
    for (int64_t k = 0; k < K; ++k) {
      for (int64_t b = 0; b < B; ++b) {
        // gather's backward: the columns land at the chosen component's mean (after the m logits)
        T* dpred = mixtures > 0 ? out.at(k, b) + mixtures + ix.at(k, b)[0] * dims : out.at(k, b);
        backward_row<T>(d.at(k, b), g.p != nullptr ? g.at(k, b) : nullptr, jr.p != nullptr ? jr.at(k, b) : nullptr,
                        mq.at(k, b), mg.p != nullptr ? mg.at(k, b) : nullptr, phi_start, phi_dim, gn.at(k, b),
                        dpred);
      }
    }
  });
}

void component_mean(const Block& out, int64_t m, int64_t dims, const Block& idx, const Block& pred, int64_t K,
                    int64_t B) {
  const auto ix = rows<int64_t>(idx);
  AT_DISPATCH_FLOATING_TYPES(out.dtype, "component_mean", [&] {
    using T = scalar_t;
    const auto o = rows<T>(out), pr = rows<T>(pred);
    for (int64_t k = 0; k < K; ++k) {
      for (int64_t b = 0; b < B; ++b) {
        const T* r = o.at(k, b);
        int64_t best = 0;
        T top = r[0];
        for (int64_t i = 1; i < m && !std::isnan(top); ++i) {
          if (std::isnan(r[i]) || r[i] > top) {
            top = r[i];
            best = i;
          }
        }
        ix.at(k, b)[0] = best;
        const T* mu = r + m + best * dims;
        std::copy(mu, mu + dims, pr.at(k, b));
      }
    }
  });
}

TipKinematics::TipKinematics(const std::vector<at::Tensor>& fk, int64_t degree, int64_t slots, int64_t monomials,
                             int64_t N)
    : signs_(fk[0]), phases_(fk[1].contiguous()), index_(fk[2].contiguous()), coef_(fk[3]), row_sums_(fk[4]),
      degree_(degree), slots_(slots), monomials_(monomials), N_(N) {
  const int64_t F = signs_.size(1);
  TORCH_CHECK(signs_.dim() == 2 && signs_.size(0) == JOINTS && phases_.numel() == F && coef_.size(1) == 24 &&
                  row_sums_.size(0) == 12 && row_sums_.size(1) == 3,
              "tip kinematics: signs (7, F), phases (F,), coef (M, 24), row_sums (12, 3)");
  TORCH_CHECK(index_.scalar_type() == at::kLong && index_.numel() == degree * slots * monomials,
              "tip kinematics: an int64 index of degree x slots x monomials");
  const int64_t* id = index_.data_ptr<int64_t>();
  for (int64_t i = 0; i < index_.numel(); ++i) TORCH_CHECK(id[i] >= 0 && id[i] < F, "tip kinematics: index range");
  const auto opt = signs_.options();
  factors_ = at::empty({N, F}, opt);
  mono_ = at::empty({N, slots * monomials}, opt);
  entries_ = at::empty({N * slots, 24}, opt);
  prod_ = at::empty({N * slots, 12}, opt);
}

// sin(q @ signs + phases) (ATen's addmm and sin), the monomials' products (multiplied in the degree's order, as
// ATen's prod), their coefficients' product, T's entries times p's, and their row sums: stm.fk._slots.
void TipKinematics::run(const Mat& q, const Mat& out) {
  const int64_t F = factors_.size(1), S = slots_ * monomials_, R = N_ * slots_;
  const auto dt = factors_.scalar_type();
  AT_DISPATCH_FLOATING_TYPES(dt, "tip_phases", [&] {
    const scalar_t* ph = phases_.data_ptr<scalar_t>();
    scalar_t* f = factors_.data_ptr<scalar_t>();
    for (int64_t r = 0; r < N_; ++r) std::copy(ph, ph + F, f + r * F);
  });
  gemm(factors_, q, signs_, 1.0);
  sin_into(factors_.data_ptr(), factors_.data_ptr(), N_ * F, dt);
  const int64_t* id = index_.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(dt, "tip_monomials", [&] {
    using T = scalar_t;
    const T* f = factors_.data_ptr<T>();
    T* mono = mono_.data_ptr<T>();
    for (int64_t r = 0; r < N_; ++r) {
      const T* fr = f + r * F;
      T* o = mono + r * S;
      for (int64_t s = 0; s < S; ++s) {
        T p = fr[id[s]];
        for (int64_t d = 1; d < degree_; ++d) p = p * fr[id[d * S + s]];
        o[s] = p;
      }
    }
  });
  gemm(entries_, Mat(mono_.data_ptr(), dt, 1, R, monomials_, 0, monomials_, 1), coef_);
  AT_DISPATCH_FLOATING_TYPES(dt, "tip_products", [&] {
    using T = scalar_t;
    const T* e = entries_.data_ptr<T>();
    T* pr = prod_.data_ptr<T>();
    for (int64_t r = 0; r < R; ++r)
      for (int64_t c = 0; c < 12; ++c) pr[r * 12 + c] = e[r * 24 + c] * e[r * 24 + 12 + c];
  });
  gemm(out, prod_, row_sums_);
}

}  // namespace stm_cpp
