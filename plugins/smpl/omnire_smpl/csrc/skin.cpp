// Linear blend skinning of Gaussians, forward and backward, one pass over the points.
//
// Per point i (M points, K joints each): the blended transform
//   T_i = sum_k w[i,k] A[slot[i], joint[i,k]]                 (3 x 4: rotation part R_i, translation t_i)
// moves the mean and turns the rotation:
//   mean_out = R_i mean + t_i,   quat_out = rotmat_to_quat(R_i) (x) quat   (Hamilton product, wxyz)
// with rotmat_to_quat exactly omnire.geometry.rotmat_to_quat's: Shepperd's method, the branch w
// when the trace is positive else the axis of the largest diagonal entry (ties to the later
// axis), the branch radicand clamped at eps with a zero gradient there (kept for parity: the
// chosen radicand is at least 1 for any finite matrix), the sign making w >= 0.
//
// In torch this is a dozen passes over the points forward and more backward (blend, einsum,
// the quaternion's stack/gather/where, the product), each with its autograd node; here every
// point is read once and written once per direction. The gradient of A is summed per thread
// (P x J x 12 each) and the threads' sums are added in thread order, so it is deterministic.
#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <vector>

namespace {

// Columns of feats = [r_w, r_x, r_y, r_z, m21 - m12, m02 - m20, m10 - m01, m01 + m10, m02 + m20,
// m12 + m21] giving (w, x, y, z) in branch b (omnire.geometry._BRANCH_COLUMNS).
constexpr int kBranchColumns[4][4] = {{0, 4, 5, 6}, {4, 1, 7, 8}, {5, 7, 2, 9}, {6, 8, 9, 3}};

template <typename S>
struct Blend {
  S T[12];  // row-major 3 x 4
};

template <typename S>
struct Quat {
  S feats[10];
  int branch;
  S sign_sq;  // the divisor: +-2 sqrt(max(r_b, eps))
  bool clamped;
  S q[4];
};

template <typename S>
inline void rotmat_to_quat(const S* T, S eps, Quat<S>& out) {
  const S m00 = T[0], m01 = T[1], m02 = T[2];
  const S m10 = T[4], m11 = T[5], m12 = T[6];
  const S m20 = T[8], m21 = T[9], m22 = T[10];
  const S t = m00 + m11 + m22;
  S* f = out.feats;
  f[0] = t + S(1);
  f[1] = (S(2) * m00 - t) + S(1);
  f[2] = (S(2) * m11 - t) + S(1);
  f[3] = (S(2) * m22 - t) + S(1);
  f[4] = m21 - m12;
  f[5] = m02 - m20;
  f[6] = m10 - m01;
  f[7] = m01 + m10;
  f[8] = m02 + m20;
  f[9] = m12 + m21;
  int b;
  if (t > S(0))
    b = 0;
  else if (m22 >= m11 && m22 >= m00)
    b = 3;
  else if (m11 >= m00)
    b = 2;
  else
    b = 1;
  out.branch = b;
  const S r = f[b];
  out.clamped = !(r >= eps);
  const S sq = S(2) * std::sqrt(out.clamped ? eps : r);
  out.sign_sq = f[kBranchColumns[b][0]] < S(0) ? -sq : sq;
  for (int c = 0; c < 4; ++c) out.q[c] = f[kBranchColumns[b][c]] / out.sign_sq;
}

// Hamilton product a (x) b, wxyz.
template <typename S>
inline void quat_mul(const S* a, const S* b, S* o) {
  o[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
  o[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
  o[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
  o[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

struct Shapes {
  int64_t P, J, M, K;
};

Shapes check(const at::Tensor& A, const at::Tensor& slot, const at::Tensor& joints, const at::Tensor& weights,
             const at::Tensor& means, const at::Tensor& quats) {
  for (const auto* t : {&A, &slot, &joints, &weights, &means, &quats})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "skin: contiguous CPU tensors expected");
  TORCH_CHECK(A.dim() == 4 && A.size(2) == 3 && A.size(3) == 4, "skin: A must be (P, J, 3, 4), got ", A.sizes());
  TORCH_CHECK(A.scalar_type() == at::kFloat || A.scalar_type() == at::kDouble, "skin: A must be float32 or float64");
  for (const auto* t : {&weights, &means, &quats})
    TORCH_CHECK(t->scalar_type() == A.scalar_type(), "skin: weights, means and quats must share A's dtype");
  TORCH_CHECK(slot.scalar_type() == at::kLong && joints.scalar_type() == at::kLong,
              "skin: slot and joint indices must be int64");
  const int64_t M = slot.size(0);
  TORCH_CHECK(slot.dim() == 1 && joints.dim() == 2 && joints.size(0) == M && weights.sizes() == joints.sizes(),
              "skin: expected slot (M,), joints (M, K), weights (M, K), got ", slot.sizes(), ", ", joints.sizes(),
              ", ", weights.sizes());
  TORCH_CHECK(means.dim() == 2 && means.size(0) == M && means.size(1) == 3, "skin: means must be (M, 3), got ",
              means.sizes());
  TORCH_CHECK(quats.dim() == 2 && quats.size(0) == M && quats.size(1) == 4, "skin: quats must be (M, 4), got ",
              quats.sizes());
  return {A.size(0), A.size(1), M, joints.size(1)};
}

// The inputs' data (checked by ``check``) and the blend of one point.
template <typename S>
struct SkinInputs {
  Shapes s;
  const S *A, *w, *x, *q;
  const int64_t *slot, *joints;
  mutable std::atomic<bool> bad{false};  // an index out of range was met
  SkinInputs(const at::Tensor& A_, const at::Tensor& slot_, const at::Tensor& joints_, const at::Tensor& weights,
             const at::Tensor& means, const at::Tensor& quats)
      : s(check(A_, slot_, joints_, weights, means, quats)), A(A_.data_ptr<S>()), w(weights.data_ptr<S>()),
        x(means.data_ptr<S>()), q(quats.data_ptr<S>()), slot(slot_.data_ptr<int64_t>()),
        joints(joints_.data_ptr<int64_t>()) {}
  // T = sum_k w_ik A[slot_i, j_ik] and the point's body; false (and ``bad`` set) when an
  // index is out of range.
  bool blend(int64_t i, Blend<S>& out, int64_t& body) const {
    body = slot[i];
    if (body < 0 || body >= s.P) return fail();
    for (int e = 0; e < 12; ++e) out.T[e] = S(0);
    for (int64_t k = 0; k < s.K; ++k) {
      const int64_t j = joints[i * s.K + k];
      if (j < 0 || j >= s.J) return fail();
      const S* a = A + (body * s.J + j) * 12;
      const S wk = w[i * s.K + k];
      for (int e = 0; e < 12; ++e) out.T[e] += wk * a[e];
    }
    return true;
  }
  bool fail() const {
    bad.store(true, std::memory_order_relaxed);
    return false;
  }
};

template <typename S>
std::vector<at::Tensor> forward_impl(const at::Tensor& A, const at::Tensor& slot, const at::Tensor& joints,
                                     const at::Tensor& weights, const at::Tensor& means, const at::Tensor& quats,
                                     double eps, int nt) {
  const SkinInputs<S> in(A, slot, joints, weights, means, quats);
  const Shapes& s = in.s;
  auto out_means = at::empty({s.M, 3}, means.options());
  auto out_quats = at::empty({s.M, 4}, quats.options());
  S* om = out_means.data_ptr<S>();
  S* oq = out_quats.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t i = 0; i < s.M; ++i) {
    Blend<S> T;
    int64_t body;
    if (!in.blend(i, T, body)) continue;
    const S* xi = in.x + i * 3;
    for (int r = 0; r < 3; ++r)
      om[i * 3 + r] = T.T[r * 4] * xi[0] + T.T[r * 4 + 1] * xi[1] + T.T[r * 4 + 2] * xi[2] + T.T[r * 4 + 3];
    Quat<S> qr;
    rotmat_to_quat(T.T, S(eps), qr);
    quat_mul(qr.q, in.q + i * 4, oq + i * 4);
  }
  TORCH_CHECK(!in.bad.load(), "skin: a body slot or joint index is out of range (P = ", s.P, ", J = ", s.J, ")");
  return {out_means, out_quats};
}

template <typename S>
std::vector<at::Tensor> backward_impl(const at::Tensor& A, const at::Tensor& slot, const at::Tensor& joints,
                                      const at::Tensor& weights, const at::Tensor& means, const at::Tensor& quats,
                                      const at::Tensor& g_means, const at::Tensor& g_quats, double eps, int nt) {
  const SkinInputs<S> in(A, slot, joints, weights, means, quats);
  const Shapes& s = in.s;
  TORCH_CHECK(g_means.sizes() == means.sizes() && g_quats.sizes() == quats.sizes() && g_means.is_contiguous() &&
                  g_quats.is_contiguous() && g_means.scalar_type() == A.scalar_type() &&
                  g_quats.scalar_type() == A.scalar_type(),
              "skin_backward: gradients shaped and typed as the outputs expected");
  auto gx_t = at::empty({s.M, 3}, means.options());
  auto gq_t = at::empty({s.M, 4}, quats.options());
  const int64_t nA = s.P * s.J * 12;
  const int threads = int(std::max<int64_t>(1, std::min<int64_t>(nt, s.M)));
  std::vector<S> partial(size_t(threads) * nA, S(0));  // per-thread dL/dA
  const S* gm = g_means.data_ptr<S>();
  const S* gqo = g_quats.data_ptr<S>();
  S* gx = gx_t.data_ptr<S>();
  S* gq = gq_t.data_ptr<S>();
#pragma omp parallel num_threads(threads)
  {
    S* gA = partial.data() + size_t(omp_get_thread_num()) * nA;
#pragma omp for schedule(static)
    for (int64_t i = 0; i < s.M; ++i) {
      Blend<S> T;
      int64_t body;
      if (!in.blend(i, T, body)) continue;
      const S* xi = in.x + i * 3;
      const S* qi = in.q + i * 4;
      const S* g = gm + i * 3;
      const S* go = gqo + i * 4;
      S gT[12];
      // mean_out = R x + t: dR = g x^T, dt = g, dx = R^T g
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) gT[r * 4 + c] = g[r] * xi[c];
        gT[r * 4 + 3] = g[r];
      }
      for (int c = 0; c < 3; ++c) gx[i * 3 + c] = T.T[c] * g[0] + T.T[4 + c] * g[1] + T.T[8 + c] * g[2];
      Quat<S> qr;
      rotmat_to_quat(T.T, S(eps), qr);
      // quat_out = qr (x) q is bilinear: dq = L(qr)^T go, dqr = Rt(q)^T go
      const S* p = qr.q;
      gq[i * 4 + 0] = p[0] * go[0] + p[1] * go[1] + p[2] * go[2] + p[3] * go[3];
      gq[i * 4 + 1] = -p[1] * go[0] + p[0] * go[1] + p[3] * go[2] - p[2] * go[3];
      gq[i * 4 + 2] = -p[2] * go[0] - p[3] * go[1] + p[0] * go[2] + p[1] * go[3];
      gq[i * 4 + 3] = -p[3] * go[0] + p[2] * go[1] - p[1] * go[2] + p[0] * go[3];
      S gp[4];
      gp[0] = qi[0] * go[0] + qi[1] * go[1] + qi[2] * go[2] + qi[3] * go[3];
      gp[1] = -qi[1] * go[0] + qi[0] * go[1] - qi[3] * go[2] + qi[2] * go[3];
      gp[2] = -qi[2] * go[0] + qi[3] * go[1] + qi[0] * go[2] - qi[1] * go[3];
      gp[3] = -qi[3] * go[0] - qi[2] * go[1] + qi[1] * go[2] + qi[0] * go[3];
      // qr = numerators / d with d = +-2 sqrt(max(r_b, eps)): dnum = gp / d; dd = -sum gp qr / d
      S gf[10] = {S(0), S(0), S(0), S(0), S(0), S(0), S(0), S(0), S(0), S(0)};
      S gd = S(0);
      for (int c = 0; c < 4; ++c) {
        gf[kBranchColumns[qr.branch][c]] += gp[c] / qr.sign_sq;
        gd -= gp[c] * p[c];
      }
      gd /= qr.sign_sq;
      if (!qr.clamped) {  // |d| = 2 sqrt(r): d|d|/dr = 1 / sqrt(r) = 2 / |d|
        const S sgn = qr.sign_sq < S(0) ? S(-1) : S(1);
        gf[qr.branch] += gd * sgn * (S(2) / std::abs(qr.sign_sq));
      }
      // feats -> the rotation entries (row-major m_rc at gT[r * 4 + c])
      const S gt = gf[0] - gf[1] - gf[2] - gf[3];  // r_w = t + 1, r_x = 2 m00 - t + 1, ...
      gT[0] += gt + S(2) * gf[1];
      gT[5] += gt + S(2) * gf[2];
      gT[10] += gt + S(2) * gf[3];
      gT[9] += gf[4] + gf[9];   // m21
      gT[6] += -gf[4] + gf[9];  // m12
      gT[2] += gf[5] + gf[8];   // m02
      gT[8] += -gf[5] + gf[8];  // m20
      gT[4] += gf[6] + gf[7];   // m10
      gT[1] += -gf[6] + gf[7];  // m01
      // T = sum_k w_k A[body, j_k]
      const int64_t* jk = in.joints + i * s.K;
      const S* wk = in.w + i * s.K;
      for (int k = 0; k < s.K; ++k) {
        S* dst = gA + (body * s.J + jk[k]) * 12;
        for (int e = 0; e < 12; ++e) dst[e] += wk[k] * gT[e];
      }
    }
  }
  TORCH_CHECK(!in.bad.load(), "skin_backward: a body slot or joint index is out of range (P = ", s.P, ", J = ", s.J, ")");
  auto gA_t = at::zeros_like(A);
  S* out = gA_t.data_ptr<S>();
  for (int th = 0; th < threads; ++th) {
    const S* src = partial.data() + size_t(th) * nA;
    for (int64_t e = 0; e < nA; ++e) out[e] += src[e];
  }
  return {gA_t, gx_t, gq_t};
}

int clamp_threads(int64_t n) { return int(std::max<int64_t>(1, std::min<int64_t>(n, 256))); }

}  // namespace

// [means_out (M, 3), quats_out (M, 4)]
std::vector<at::Tensor> skin_forward(at::Tensor A, at::Tensor slot, at::Tensor joints, at::Tensor weights,
                                     at::Tensor means, at::Tensor quats, double eps, int64_t nthreads) {
  if (A.scalar_type() == at::kDouble)
    return forward_impl<double>(A, slot, joints, weights, means, quats, eps, clamp_threads(nthreads));
  return forward_impl<float>(A, slot, joints, weights, means, quats, eps, clamp_threads(nthreads));
}

// [dL/dA (P, J, 3, 4), dL/dmeans (M, 3), dL/dquats (M, 4)]
std::vector<at::Tensor> skin_backward(at::Tensor A, at::Tensor slot, at::Tensor joints, at::Tensor weights,
                                      at::Tensor means, at::Tensor quats, at::Tensor g_means, at::Tensor g_quats,
                                      double eps, int64_t nthreads) {
  if (A.scalar_type() == at::kDouble)
    return backward_impl<double>(A, slot, joints, weights, means, quats, g_means, g_quats, eps,
                                 clamp_threads(nthreads));
  return backward_impl<float>(A, slot, joints, weights, means, quats, g_means, g_quats, eps,
                              clamp_threads(nthreads));
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("skin_forward", &skin_forward, "blend-skinned Gaussian means and rotations");
  m.def("skin_backward", &skin_backward, "gradient of skin_forward");
}
