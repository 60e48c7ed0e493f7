// Native SSIM map of two (H, W, C) images and its gradient with respect to the first
// (the rendered image; the target takes no gradient). Same definition as
// omnire.losses.ssim_map: a separable Gaussian window (weights given by the caller), reflect
// padding (index -1 -> 1, torch's "reflect"), c1 = 0.01^2, c2 = 0.03^2, mean over channels.
//
// The torch composition spends most of its time in generic depthwise convolutions, the
// reflection padding's backward and a dozen elementwise passes over the image; here each
// pass is one loop over contiguous rows that the compiler vectorises, and the backward blurs
// only the three statistics that depend on the first image (mu_x, E[x^2], E[xy]).
#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <vector>

namespace {

// Reflect an index of the padded signal into [0, n): -k -> k, n - 1 + k -> n - 1 - k.
inline int reflect(int k, int n) {
  if (k < 0) return -k;
  if (k >= n) return 2 * (n - 1) - k;
  return k;
}

// out[j] = sum_u g[u] in[reflect(j + u - p)], j in [0, n); ``pad`` scratch of n + 2p.
template <typename S>
inline void blur_row(const S* in, S* out, int n, const S* g, int p, S* pad) {
  for (int j = 0; j < n + 2 * p; ++j) pad[j] = in[reflect(j - p, n)];
  for (int j = 0; j < n; ++j) out[j] = S(0);
  for (int u = 0; u <= 2 * p; ++u) {
    const S w = g[u];
    const S* src = pad + u;
    for (int j = 0; j < n; ++j) out[j] += w * src[j];
  }
}

// Adjoint of blur_row: out[q] = sum over (j, u) with reflect(j + u - p) = q of g[u] in[j].
// The padded adjoint gp[m] = sum_u g[u] in[m - u] (m in [0, n + 2p)) comes from the input
// zero-padded by 2p on both sides (``pad``: n + 4p), then the padding folds back.
template <typename S>
inline void blur_row_adjoint(const S* in, S* out, int n, const S* g, int p, S* pad, S* gp) {
  const int m = n + 2 * p;
  for (int j = 0; j < n + 4 * p; ++j) pad[j] = (j >= 2 * p && j < 2 * p + n) ? in[j - 2 * p] : S(0);
  for (int j = 0; j < m; ++j) gp[j] = S(0);
  for (int u = 0; u <= 2 * p; ++u) {
    const S w = g[u];
    const S* src = pad + 2 * p - u;  // gp[j] += g[u] in[j - u]
    for (int j = 0; j < m; ++j) gp[j] += w * src[j];
  }
  for (int q = 0; q < n; ++q) out[q] = gp[q + p];
  for (int j = 0; j < p; ++j) out[reflect(j - p, n)] += gp[j];
  for (int j = n + p; j < m; ++j) out[reflect(j - p, n)] += gp[j];
}

// Weighted sums of rows over P planes of H x W: out[q] = sum over taps[q] of w * in[r], for
// (r, w) in taps[q]. Gathered per output row, so no two threads write one row.
template <typename S>
using RowTaps = std::vector<std::vector<std::pair<int, S>>>;

template <typename S>
void sum_rows(const S* in, S* out, int P, int H, int W, const RowTaps<S>& taps, int nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t pq = 0; pq < int64_t(P) * H; ++pq) {
    const int64_t plane = pq / H;
    const int q = int(pq % H);
    const S* base = in + plane * H * W;
    S* o = out + plane * H * W + int64_t(q) * W;
    for (int j = 0; j < W; ++j) o[j] = S(0);
    for (const auto& [r, w] : taps[q]) {
      const S* src = base + int64_t(r) * W;
      for (int j = 0; j < W; ++j) o[j] += w * src[j];
    }
  }
}

// The vertical pass, out[q] = sum_u g[u] in[reflect(q + u - p)], as row taps; with
// ``adjoint`` its transpose, out[q] = sum over (r, u) with reflect(r + u - p) = q of
// g[u] in[r] (a border row also takes the rows whose reflected taps land on it).
template <typename S>
RowTaps<S> column_taps(int H, const S* g, int p, bool adjoint) {
  RowTaps<S> taps(H);
  for (int r = 0; r < H; ++r)
    for (int u = 0; u <= 2 * p; ++u) {
      const int q = reflect(r + u - p, H);
      if (adjoint)
        taps[q].push_back({r, g[u]});
      else
        taps[r].push_back({q, g[u]});
    }
  return taps;
}

// Horizontal pass (or its adjoint) over every row of P planes.
template <typename S>
void blur_rows(const S* in, S* out, int P, int H, int W, const S* g, int p, bool adjoint, int nthreads) {
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<S> pad(W + 4 * p), gp(W + 2 * p);
#pragma omp for schedule(static)
    for (int64_t pr = 0; pr < int64_t(P) * H; ++pr) {
      const S* src = in + pr * W;
      S* dst = out + pr * W;
      if (adjoint)
        blur_row_adjoint(src, dst, W, g, p, pad.data(), gp.data());
      else
        blur_row(src, dst, W, g, p, pad.data());
    }
  }
}

constexpr double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;

void check_inputs(const at::Tensor& a, const at::Tensor& b, const at::Tensor& window) {
  TORCH_CHECK(a.device().is_cpu() && b.device().is_cpu(), "ssim: CPU tensors expected");
  TORCH_CHECK(a.dim() == 3 && a.sizes() == b.sizes(), "ssim: expected two (H, W, C) images of one shape, got ",
              a.sizes(), " and ", b.sizes());
  TORCH_CHECK(a.scalar_type() == b.scalar_type() && a.scalar_type() == window.scalar_type() &&
                  (a.scalar_type() == at::kFloat || a.scalar_type() == at::kDouble),
              "ssim: images and window must share one dtype, float32 or float64");
  TORCH_CHECK(a.is_contiguous() && b.is_contiguous() && window.is_contiguous(), "ssim: contiguous tensors expected");
  TORCH_CHECK(window.dim() == 1 && window.size(0) % 2 == 1, "ssim: window must be (odd,)");
  const int64_t p = window.size(0) / 2;
  TORCH_CHECK(a.size(0) > p && a.size(1) > p, "ssim: image ", a.size(0), "x", a.size(1),
              " too small for reflect padding of ", p);
}

template <typename S>
std::vector<at::Tensor> forward_impl(const at::Tensor& a, const at::Tensor& b, const at::Tensor& window, int nt) {
  const int H = int(a.size(0)), W = int(a.size(1)), C = int(a.size(2));
  const int p = int(window.size(0) / 2);
  const S* g = window.data_ptr<S>();
  const S* x = a.data_ptr<S>();
  const S* y = b.data_ptr<S>();
  const int64_t n = int64_t(H) * W;
  // 5C planes in the order [x, y, x^2, y^2, xy] x C
  auto raw = at::empty({5 * C, H, W}, a.options());
  S* s = raw.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t i = 0; i < n; ++i)
    for (int c = 0; c < C; ++c) {
      const S xv = x[i * C + c], yv = y[i * C + c];
      s[(0 * C + c) * n + i] = xv;
      s[(1 * C + c) * n + i] = yv;
      s[(2 * C + c) * n + i] = xv * xv;
      s[(3 * C + c) * n + i] = yv * yv;
      s[(4 * C + c) * n + i] = xv * yv;
    }
  auto tmp = at::empty_like(raw);
  blur_rows(s, tmp.data_ptr<S>(), 5 * C, H, W, g, p, false, nt);
  auto stats = at::empty_like(raw);  // blurred: [mu_x, mu_y, E[x^2], E[y^2], E[xy]] x C
  sum_rows(tmp.data_ptr<S>(), stats.data_ptr<S>(), 5 * C, H, W, column_taps(H, g, p, false), nt);
  auto map = at::empty({H, W, 1}, a.options());
  S* mp = map.data_ptr<S>();
  const S* st = stats.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t i = 0; i < n; ++i) {
    S acc = S(0);
    for (int c = 0; c < C; ++c) {
      const S mx = st[(0 * C + c) * n + i], my = st[(1 * C + c) * n + i];
      const S vx = st[(2 * C + c) * n + i] - mx * mx, vy = st[(3 * C + c) * n + i] - my * my;
      const S cov = st[(4 * C + c) * n + i] - mx * my;
      acc += ((S(2) * mx * my + S(C1)) * (S(2) * cov + S(C2))) / ((mx * mx + my * my + S(C1)) * (vx + vy + S(C2)));
    }
    mp[i] = acc / S(C);
  }
  return {map, stats};
}

template <typename S>
at::Tensor backward_impl(const at::Tensor& a, const at::Tensor& b, const at::Tensor& window, const at::Tensor& stats,
                         const at::Tensor& g_map, int nt) {
  const int H = int(a.size(0)), W = int(a.size(1)), C = int(a.size(2));
  const int p = int(window.size(0) / 2);
  const S* g = window.data_ptr<S>();
  const int64_t n = int64_t(H) * W;
  const S* st = stats.data_ptr<S>();
  const S* gm = g_map.data_ptr<S>();
  // dL/d(blurred mu_x, E[x^2], E[xy]) per channel: 3C planes [mu_x, x^2, xy] x C
  auto gstat = at::empty({3 * C, H, W}, a.options());
  S* gs = gstat.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t i = 0; i < n; ++i) {
    const S gi = gm[i] / S(C);
    for (int c = 0; c < C; ++c) {
      const S mx = st[(0 * C + c) * n + i], my = st[(1 * C + c) * n + i];
      const S vx = st[(2 * C + c) * n + i] - mx * mx, vy = st[(3 * C + c) * n + i] - my * my;
      const S cov = st[(4 * C + c) * n + i] - mx * my;
      const S A1 = S(2) * mx * my + S(C1), A2 = S(2) * cov + S(C2);
      const S B1 = mx * mx + my * my + S(C1), B2 = vx + vy + S(C2);
      const S m = (A1 * A2) / (B1 * B2);
      // m = A1 A2 / (B1 B2): partials through A1 (mu_x), A2 (cov), B1 (mu_x), B2 (var_x)
      const S a1 = gi * A2 / (B1 * B2), a2 = gi * A1 / (B1 * B2);
      const S b1 = -gi * m / B1, b2 = -gi * m / B2;
      const S g_cov = S(2) * a2, g_vx = b2;
      // cov = E[xy] - mu_x mu_y, var_x = E[x^2] - mu_x^2
      gs[(0 * C + c) * n + i] = S(2) * my * a1 + S(2) * mx * b1 - my * g_cov - S(2) * mx * g_vx;
      gs[(1 * C + c) * n + i] = g_vx;
      gs[(2 * C + c) * n + i] = g_cov;
    }
  }
  // adjoint of (columns after rows) = rows-adjoint after columns-adjoint
  auto tmp = at::empty_like(gstat);
  sum_rows(gs, tmp.data_ptr<S>(), 3 * C, H, W, column_taps(H, g, p, true), nt);
  blur_rows(tmp.data_ptr<S>(), gs, 3 * C, H, W, g, p, true, nt);
  auto g_a = at::empty_like(a);
  S* ga = g_a.data_ptr<S>();
  const S* x = a.data_ptr<S>();
  const S* y = b.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t i = 0; i < n; ++i)
    for (int c = 0; c < C; ++c)
      ga[i * C + c] = gs[(0 * C + c) * n + i] + S(2) * x[i * C + c] * gs[(1 * C + c) * n + i] +
                      y[i * C + c] * gs[(2 * C + c) * n + i];
  return g_a;
}

}  // namespace

// Returns [ssim map (H, W, 1), blurred statistics (5C, H, W)] (the latter for ssim_backward).
std::vector<at::Tensor> ssim_forward(at::Tensor a, at::Tensor b, at::Tensor window, int64_t nthreads) {
  check_inputs(a, b, window);
  const int nt = int(std::max<int64_t>(1, std::min<int64_t>(nthreads, 256)));
  if (a.scalar_type() == at::kFloat) return forward_impl<float>(a, b, window, nt);
  return forward_impl<double>(a, b, window, nt);
}

// dL/da (H, W, C) from dL/dmap (H, W, 1) and ssim_forward's statistics.
at::Tensor ssim_backward(at::Tensor a, at::Tensor b, at::Tensor window, at::Tensor stats, at::Tensor g_map,
                         int64_t nthreads) {
  check_inputs(a, b, window);
  TORCH_CHECK(stats.scalar_type() == a.scalar_type() && stats.is_contiguous() &&
                  stats.sizes() == at::IntArrayRef({5 * a.size(2), a.size(0), a.size(1)}),
              "ssim_backward: statistics of ssim_forward expected");
  TORCH_CHECK(g_map.scalar_type() == a.scalar_type() && g_map.is_contiguous() && g_map.numel() == a.size(0) * a.size(1),
              "ssim_backward: dL/dmap (H, W, 1) expected");
  const int nt = int(std::max<int64_t>(1, std::min<int64_t>(nthreads, 256)));
  if (a.scalar_type() == at::kFloat) return backward_impl<float>(a, b, window, stats, g_map, nt);
  return backward_impl<double>(a, b, window, stats, g_map, nt);
}
