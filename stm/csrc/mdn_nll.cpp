// The MDN head's training loss, stm.mdn.mixture_nll(*stm.mdn.split_params(raw, m, D, sigma_min), target), as one
// pass over each row of raw head outputs (N, m (D + 2)) [logits (m), sigma pre-activations (m), means (m, D)] and
// targets (N, D), forward and backward (edit with mdn_nll.h: the build is keyed on the sources only).
//
// Why: in ATen the split, softplus, log_softmax, component log-densities and logsumexp are ~15 calls forward and
// more backward, each a pass over N m D elements in memory; here the row's m D means are read once forward and once
// backward (where their gradients are written), and the rest works on (N, m) buffers: plain loops, with the
// exponentials and logarithms as ATen calls over a whole buffer (vectorised, which loops built without
// -march flags are not).
//
// The same maths as stm.mdn, in the same order where it matters for rounding: sigma = sigma_min + softplus(x) (the
// softplus of torch, linear above 20), log-softmax of the logits and a max-shifted log-sum-exp over components (an
// infinite max shifts by 0, as torch.logsumexp), so extreme sigmas and far targets give large but finite numbers.
// The backward is closed form, per row with upstream gradient g and responsibilities r_i = exp(a_i - lse):
//   d/d logit_i = g (alpha_i - r_i), d/d mu_id = g r_i (mu_id - t_d) / sigma_i^2,
//   d/d x_i = g r_i (D - |t - mu_i|^2 / sigma_i^2) sigmoid(x_i) / sigma_i, d/d t = -sum_i d/d mu_i,
// from three numbers per component saved by the forward (`coef`, (N, m, 3)).
#include "mdn_nll.h"

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <limits>

namespace stm_cpp {
namespace {

constexpr int64_t GRAIN = 64;  // rows per parallel chunk
constexpr int64_t LANES = 8;  // partial sums of a squared distance
// Exponents below CUT are raised to it before ATen's exp: below about -87 float32's exp leaves the normal range and
// its vectorised path slows a hundredfold (and the Python path, whose logsumexp meets such exponents for every
// far component, pays it too). exp(CUT) ~ 2e-35 next to a largest term of 1 changes no sum; what it gives a far
// component's responsibility or weight instead of a smaller number moves a gradient by ~1e-35 times its scale.
constexpr double CUT = -80.0;
constexpr double LOG_2PI = 1.8378770664093454835606594728112;

// What the forward's passes share: per component (N, m) the shifted logits' exponentials `e`, exp(x) `z`, sigma
// `s`, |t - mu_i|^2 `sq` and the shifted log-densities' exponentials `a`; per row the logits' max and the shift.
// The transcendental functions run as ATen calls on these (N m) buffers, which vectorise them; the loops here
// do the rest, row by row.
template <typename T>
struct Buffers {
  T *e, *z, *s, *sq, *a, *lmax, *shift;
};

// |t - mu|^2 over D coordinates, in LANES independent partial sums (a single running sum is a chain of dependent
// additions that the compiler may not reorder; these it vectorises).
template <typename T>
inline T squared_distance(const T* t, const T* mu, int64_t D) {
  T acc[LANES] = {};
  int64_t d = 0;
  for (; d + LANES <= D; d += LANES)
    for (int64_t j = 0; j < LANES; ++j) {
      const T diff = t[d + j] - mu[d + j];
      acc[j] += diff * diff;
    }
  for (int64_t j = 0; d < D; ++d, ++j) {
    const T diff = t[d] - mu[d];
    acc[j] += diff * diff;
  }
  T sum = T(0);
  for (int64_t j = 0; j < LANES; ++j) sum += acc[j];
  return sum;
}

// Pass 1, per row: the logits' max and logit - max (to exponentiate), x (to exponentiate), |t - mu_i|^2.
template <typename T>
void pass_inputs(const T* raw, const T* tgt, const Buffers<T>& b, int64_t begin, int64_t end, int64_t m, int64_t D) {
  const int64_t P = m * (D + 2);
  const T cut = T(CUT);
  for (int64_t r = begin; r < end; ++r) {
    const T* la = raw + r * P;
    const T* mu = la + 2 * m;
    const T* t = tgt + r * D;
    T lmax = la[0];
    for (int64_t i = 1; i < m; ++i) lmax = std::max(lmax, la[i]);
    b.lmax[r] = lmax;
    for (int64_t i = 0; i < m; ++i) {
      b.e[r * m + i] = std::max(la[i] - lmax, cut);
      b.z[r * m + i] = std::max(la[m + i], cut);
      b.sq[r * m + i] = squared_distance(t, mu + i * D, D);
    }
  }
}

// Between (after e = exp(e), z = exp(x), sp = log1p(z)): sigma = sigma_min + softplus(x), torch's softplus (x
// above 20, else log1p(exp(x))), in place of sp.
template <typename T>
void pass_sigma(const T* raw, T* s, int64_t begin, int64_t end, int64_t m, int64_t D, T sigma_min) {
  const int64_t P = m * (D + 2);
  for (int64_t r = begin; r < end; ++r) {
    const T* xs = raw + r * P + m;
    T* sr = s + r * m;
    for (int64_t i = 0; i < m; ++i) sr[i] = sigma_min + (xs[i] > T(20) ? xs[i] : sr[i]);
  }
}

// Pass 2 (after ls = log(s)), per row: log alpha_i + log g_i(t) - shift,
// shift = their max (0 where infinite, as torch.logsumexp); the softmax's sum is kept in lmax's place as
// lmax + log(sum).
template <typename T>
void pass_densities(const T* raw, const T* ls, const Buffers<T>& b, int64_t begin, int64_t end, int64_t m,
                    int64_t D) {
  const int64_t P = m * (D + 2);
  const T norm = T(-0.5 * static_cast<double>(D) * LOG_2PI);
  const T dim = T(D);
  for (int64_t r = begin; r < end; ++r) {
    const T* la = raw + r * P;
    T se = T(0);
    for (int64_t i = 0; i < m; ++i) se += b.e[r * m + i];
    const T lse_a = b.lmax[r] + std::log(se);
    T amax = -std::numeric_limits<T>::infinity();
    for (int64_t i = 0; i < m; ++i) {
      const int64_t k = r * m + i;
      const T iv = T(1) / (b.s[k] * b.s[k]);
      b.a[k] = (la[i] - lse_a) + ((norm - dim * ls[k]) - T(0.5) * b.sq[k] * iv);
      amax = std::max(amax, b.a[k]);
    }
    const T shift = std::isinf(amax) ? T(0) : amax;
    b.shift[r] = shift;
    b.lmax[r] = se;
    for (int64_t i = 0; i < m; ++i) b.a[r * m + i] = std::max(b.a[r * m + i] - shift, T(CUT));
  }
}

// Pass 3 (after a = exp(a)), per row: the NLL and, where asked, the backward's three numbers per component.
template <typename T>
void pass_output(const T* raw, const Buffers<T>& b, T* nll, T* coef, int64_t begin, int64_t end, int64_t m,
                 int64_t D) {
  const int64_t P = m * (D + 2);
  const T dim = T(D);
  for (int64_t r = begin; r < end; ++r) {
    T sr = T(0);
    for (int64_t i = 0; i < m; ++i) sr += b.a[r * m + i];
    nll[r] = -(b.shift[r] + std::log(sr));
    if (coef == nullptr) continue;
    const T* xs = raw + r * P + m;
    const T inv_sr = T(1) / sr, inv_se = T(1) / b.lmax[r];
    T* c = coef + r * m * 3;
    for (int64_t i = 0; i < m; ++i) {
      const int64_t k = r * m + i;
      const T resp = b.a[k] * inv_sr;
      const T s = b.s[k], iv = T(1) / (s * s);
      const T sig = xs[i] > T(20) ? T(1) : b.z[k] / (b.z[k] + T(1));  // softplus' derivative, as torch's backward
      c[3 * i] = b.e[k] * inv_se - resp;
      c[3 * i + 1] = resp * iv;
      c[3 * i + 2] = resp * (dim - b.sq[k] * iv) * sig * (s * iv);
    }
  }
}

template <typename T>
void backward_rows(const T* grad, const T* raw, const T* tgt, const T* coef, T* graw, T* gtgt, int64_t begin,
                   int64_t end, int64_t m, int64_t D) {
  const int64_t P = m * (D + 2);
  for (int64_t r = begin; r < end; ++r) {
    const T g = grad[r];
    const T* mu = raw + r * P + 2 * m;
    const T* t = tgt + r * D;
    const T* c = coef + r * m * 3;
    T* gr = graw + r * P;
    T* gmu = gr + 2 * m;
    T* gt = gtgt == nullptr ? nullptr : gtgt + r * D;
    if (gt != nullptr)
      for (int64_t d = 0; d < D; ++d) gt[d] = T(0);
    for (int64_t i = 0; i < m; ++i) {
      gr[i] = g * c[3 * i];
      gr[m + i] = g * c[3 * i + 2];
      const T w = g * c[3 * i + 1];
      const T* mi = mu + i * D;
      T* gi = gmu + i * D;
      for (int64_t d = 0; d < D; ++d) gi[d] = w * (mi[d] - t[d]);
      if (gt != nullptr)
        for (int64_t d = 0; d < D; ++d) gt[d] -= gi[d];
    }
  }
}

void check(const at::Tensor& raw, const at::Tensor& target, int64_t m) {
  TORCH_CHECK(raw.dim() == 2 && target.dim() == 2 && raw.size(0) == target.size(0),
              "mdn_nll: raw (N, P), target (N, D)");
  TORCH_CHECK(m >= 1 && raw.size(1) == m * (target.size(1) + 2), "mdn_nll: raw has m (D + 2) columns");
  TORCH_CHECK(raw.is_contiguous() && target.is_contiguous() && raw.device().is_cpu(), "mdn_nll: contiguous CPU");
  TORCH_CHECK(raw.scalar_type() == target.scalar_type(), "mdn_nll: raw and target of one dtype");
}

}  // namespace

std::tuple<at::Tensor, at::Tensor> mdn_nll_forward(const at::Tensor& raw, const at::Tensor& target, int64_t mixtures,
                                                   double sigma_min, bool need_coef) {
  check(raw, target, mixtures);
  const int64_t N = raw.size(0), D = target.size(1), m = mixtures;
  auto nll = at::empty({N}, raw.options());
  at::Tensor coef = need_coef ? at::empty({N, m, 3}, raw.options()) : at::Tensor();
  auto e = at::empty({N, m}, raw.options()), z = at::empty_like(e), sq = at::empty_like(e), a = at::empty_like(e);
  auto rows = at::empty({2, N}, raw.options());
  AT_DISPATCH_FLOATING_TYPES(raw.scalar_type(), "mdn_nll_forward", [&] {
    const scalar_t* x = raw.data_ptr<scalar_t>();
    const scalar_t* t = target.data_ptr<scalar_t>();
    Buffers<scalar_t> b{e.data_ptr<scalar_t>(), z.data_ptr<scalar_t>(), nullptr, sq.data_ptr<scalar_t>(),
                        a.data_ptr<scalar_t>(), rows.data_ptr<scalar_t>(), rows.data_ptr<scalar_t>() + N};
    at::parallel_for(0, N, GRAIN, [&](int64_t begin, int64_t end) {
      pass_inputs<scalar_t>(x, t, b, begin, end, m, D);
    });
    e.exp_();
    z.exp_();
    auto s = at::log1p(z);
    b.s = s.data_ptr<scalar_t>();
    at::parallel_for(0, N, GRAIN, [&](int64_t begin, int64_t end) {
      pass_sigma<scalar_t>(x, b.s, begin, end, m, D, static_cast<scalar_t>(sigma_min));
    });
    auto ls = at::log(s);
    const scalar_t* lsp = ls.data_ptr<scalar_t>();
    at::parallel_for(0, N, GRAIN, [&](int64_t begin, int64_t end) {
      pass_densities<scalar_t>(x, lsp, b, begin, end, m, D);
    });
    a.exp_();
    scalar_t* out = nll.data_ptr<scalar_t>();
    scalar_t* c = need_coef ? coef.data_ptr<scalar_t>() : nullptr;
    at::parallel_for(0, N, GRAIN, [&](int64_t begin, int64_t end) {
      pass_output<scalar_t>(x, b, out, c, begin, end, m, D);
    });
  });
  return {nll, coef};
}

std::tuple<at::Tensor, at::Tensor> mdn_nll_backward(const at::Tensor& grad, const at::Tensor& raw,
                                                    const at::Tensor& target, const at::Tensor& coef,
                                                    int64_t mixtures, bool need_target) {
  check(raw, target, mixtures);
  const int64_t N = raw.size(0), D = target.size(1);
  TORCH_CHECK(coef.defined() && coef.numel() == N * mixtures * 3, "mdn_nll_backward: the forward saved no coef");
  auto g = grad.contiguous().to(raw.scalar_type());
  TORCH_CHECK(g.numel() == N, "mdn_nll_backward: one gradient per row");
  auto graw = at::empty_like(raw);
  at::Tensor gtgt = need_target ? at::empty_like(target) : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(raw.scalar_type(), "mdn_nll_backward", [&] {
    const scalar_t* gp = g.data_ptr<scalar_t>();
    const scalar_t* x = raw.data_ptr<scalar_t>();
    const scalar_t* t = target.data_ptr<scalar_t>();
    const scalar_t* c = coef.data_ptr<scalar_t>();
    scalar_t* gx = graw.data_ptr<scalar_t>();
    scalar_t* gt = need_target ? gtgt.data_ptr<scalar_t>() : nullptr;
    at::parallel_for(0, N, GRAIN, [&](int64_t begin, int64_t end) {
      backward_rows<scalar_t>(gp, x, t, c, gx, gt, begin, end, mixtures, D);
    });
  });
  return {graw, gtgt};
}

}  // namespace stm_cpp
