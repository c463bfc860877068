// The fed-back state's elementwise part: see feedback_state.h. (Edit this file with the header: the build is keyed
// on the sources only.)
#include "feedback_state.h"

#include <ATen/Dispatch.h>

#include <algorithm>
#include <cmath>

#include "rows.h"

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

at::Tensor monomial_products(const at::Tensor& factors, const at::Tensor& index, int64_t degree) {
  const auto f = factors.contiguous();
  const auto ix = index.contiguous();
  TORCH_CHECK(ix.scalar_type() == at::kLong && ix.numel() % degree == 0, "monomial_products: int64 index");
  const int64_t N = f.size(0), F = f.size(1), S = ix.numel() / degree;
  auto mono = at::empty({N, S}, f.options());
  const int64_t* id = ix.data_ptr<int64_t>();
  for (int64_t i = 0; i < ix.numel(); ++i) {
    TORCH_CHECK(id[i] >= 0 && id[i] < F, "monomial_products: index out of range");
  }
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "monomial_products", [&] {
    using T = scalar_t;
    for (int64_t r = 0; r < N; ++r) {
      const T* fr = f.data_ptr<T>() + r * F;
      T* out = mono.data_ptr<T>() + r * S;
      for (int64_t s = 0; s < S; ++s) {
        T p = fr[id[s]];
        for (int64_t d = 1; d < degree; ++d) p = p * fr[id[d * S + s]];
        out[s] = p;
      }
    }
  });
  return mono;
}

void fed_joints(const Block& q_prev, const at::Tensor& pred, const Block& lower, const Block& upper,
                const Block& mean, const Block& q, const Block& mask_q, const Block& x, const Block& mask_g) {
  const int64_t K = pred.size(0), B = pred.size(1);
  const auto mq = rows<bool>(mask_q), mg = rows<bool>(mask_g);
  AT_DISPATCH_FLOATING_TYPES(pred.scalar_type(), "fed_joints", [&] {
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

void fed_context(const at::Tensor& phi_src, const Block& offset, const Block& psi, int64_t psi_dim, const Block& mean,
                 int64_t phi_start, const Block& x) {
  const int64_t K = phi_src.size(0), B = phi_src.size(1), phi_dim = phi_src.size(2), P = psi_dim;
  AT_DISPATCH_FLOATING_TYPES(phi_src.scalar_type(), "fed_context", [&] {
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
                  const at::Tensor& gq_new, const Block& dout) {
  const int64_t K = gq_new.size(0), B = gq_new.size(1);
  const auto mq = rows<bool>(mask_q), mg = rows<bool>(mask_g);
  const auto ix = rows<int64_t>(idx);
  AT_DISPATCH_FLOATING_TYPES(gq_new.scalar_type(), "fed_backward", [&] {
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

}  // namespace stm_cpp
