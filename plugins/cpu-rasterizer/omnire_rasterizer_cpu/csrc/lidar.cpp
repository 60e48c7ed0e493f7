// Native LiDAR rendering for omnire's cpu rasterizer: the ``lidar`` capability of
// omnire/rasterization.py, with the geometry of omnire/lidarprojection.py.
//
// lidar_project: each Gaussian to the sensor's sphere (computed in double): its direction
// (azimuth, elevation, degrees), the inverse angular covariance (conic a, b, c), the range
// quadric (quad xx xy xz yy yz zz, lin x y z: t* = d.lin / d^T quad d), its centre distance
// and angular extents; lidar_project_backward its gradient to means, quaternions, scales
// (one pass over the Gaussians where torch would take dozens of small operations).
// lidar_forward: bin Gaussians (in the caller's order of centre distance) and rays into
// tiles of the sphere and composite the rays of each tile over its list (each Gaussian of
// the list against every live ray of the tile, the exponents in a loop the compiler
// vectorises); lidar_backward: that compositing's gradient to the projected quantities.
// OpenMP over tiles and over Gaussians.
//
// Two instantiations: float (training) and double (gradient checks). The forward and the
// backward take every skip / stop decision with the same operations (compiled with
// -ffp-contract=off), so the backward walks exactly the pairs the forward composited.
#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double ALPHA_MIN = 1.0 / 255.0;
constexpr double ALPHA_MAX = 0.99;
constexpr double T_MIN = 1e-4;
constexpr double MIN_DEN = 1e-12;  // omnire/lidarprojection.py MIN_RANGE_DENOMINATOR

// Packed record per Gaussian (REC values of the kernel's type).
enum { R_AZ = 0, R_EL, R_CA, R_CB, R_CC, R_OP, R_FLOOR, R_Q, R_L = R_Q + 6, REC = R_L + 3 };
// Gradient slots per Gaussian: the record's differentiable values, then the F features.
enum { G_AZ = 0, G_EL, G_CA, G_CB, G_CC, G_OP, G_Q, G_L = G_Q + 6, G_F = G_L + 3 };

void check(const at::Tensor& t, at::ScalarType st, const char* name, int64_t rows, int64_t cols) {
  TORCH_CHECK(t.device().is_cpu() && t.is_contiguous(), name, " must be a contiguous CPU tensor");
  TORCH_CHECK(t.scalar_type() == st, name, " has dtype ", t.scalar_type(), ", expected ", st);
  TORCH_CHECK(t.size(0) == rows && (cols < 0 ? t.dim() == 1 : (t.dim() == 2 && t.size(1) == cols)), name,
              " has the wrong shape");
}

// CSR lists: for each tile, the items that fall in it (offsets (tiles + 1), items).
struct Lists {
  at::Tensor off;    // (tiles + 1,) int64
  at::Tensor items;  // (M,) int32 Gaussian ids or int64 ray ids
};

// Each Gaussian of ``order`` (already sorted by centre distance) into every tile of its box
// (first column, columns modulo ``columns``, first row, rows): per tile in that order.
Lists bin_gaussians(const int64_t* order, int64_t n, const int64_t* box, int64_t columns, int64_t tiles) {
  at::Tensor off = at::zeros({tiles + 1}, at::kLong);
  int64_t* o = off.data_ptr<int64_t>();
  auto each_tile = [&](int64_t g, auto&& fn) {
    const int64_t* b = box + 4 * g;
    for (int64_t r = 0; r < b[3]; ++r)
      for (int64_t c = 0; c < b[1]; ++c) fn((b[2] + r) * columns + (b[0] + c) % columns);
  };
  for (int64_t k = 0; k < n; ++k) each_tile(order[k], [&](int64_t t) { ++o[t + 1]; });
  for (int64_t t = 0; t < tiles; ++t) o[t + 1] += o[t];
  at::Tensor items = at::empty({o[tiles]}, at::kInt);
  int32_t* it = items.data_ptr<int32_t>();
  std::vector<int64_t> cursor(o, o + tiles);
  for (int64_t k = 0; k < n; ++k) {
    const int64_t g = order[k];
    each_tile(g, [&](int64_t t) { it[cursor[t]++] = int32_t(g); });
  }
  return {off, items};
}

// Rays by tile (counting sort; within a tile in index order).
Lists bin_rays(const int64_t* tile, int64_t R, int64_t tiles) {
  at::Tensor off = at::zeros({tiles + 1}, at::kLong);
  int64_t* o = off.data_ptr<int64_t>();
  for (int64_t j = 0; j < R; ++j) ++o[tile[j] + 1];
  for (int64_t t = 0; t < tiles; ++t) o[t + 1] += o[t];
  at::Tensor items = at::empty({R}, at::kLong);
  int64_t* it = items.data_ptr<int64_t>();
  std::vector<int64_t> cursor(o, o + tiles);
  for (int64_t j = 0; j < R; ++j) it[cursor[tile[j]]++] = j;
  return {off, items};
}

// The walk of one tile's rays over its list: the rays gathered (azimuth in [0, 360),
// elevation, direction) and the state the forward and the backward share per ray
// (transmittance, still composited, median found) with scratch for the exponents.
template <typename S>
struct TileWalk {
  std::vector<int64_t> id;
  std::vector<S> az, el, u, T, pw;  // u: (P, 3)
  std::vector<uint8_t> alive, crossed;
  int64_t live = 0;
  // Gather the rays of ``tile`` and reset their state; returns their number.
  int64_t start(const Lists& rl, int64_t tile, const S* ray_az, const S* ray_el, const S* dirs) {
    const int64_t* off = rl.off.data_ptr<int64_t>();
    const int64_t* ids = rl.items.data_ptr<int64_t>();
    const int64_t P = off[tile + 1] - off[tile];
    id.assign(ids + off[tile], ids + off[tile + 1]);
    az.resize(P);
    el.resize(P);
    u.resize(3 * P);
    for (int64_t k = 0; k < P; ++k) {
      const int64_t j = id[k];
      az[k] = ray_az[j];
      el[k] = ray_el[j];
      for (int c = 0; c < 3; ++c) u[3 * k + c] = dirs[3 * j + c];
    }
    T.assign(P, S(1));
    pw.resize(P);
    alive.assign(P, 1);
    crossed.assign(P, 0);
    live = P;
    return P;
  }
};

// Azimuth offset ray - Gaussian in [-180, 180): both in [0, 360), so one turn fixes it.
template <typename S>
inline S azimuth_offset(S ray, S gaussian) {
  const S dx = ray - gaussian;
  return dx >= S(180) ? dx - S(360) : (dx < S(-180) ? dx + S(360) : dx);
}

// Exponent of Gaussian g at every ray of the tile (a plain loop the compiler vectorises;
// the forward and the backward both call it, so their decisions agree bit for bit).
template <typename S>
inline void powers(const S* g, const TileWalk<S>& tr, S* pw) {
  const S gaz = g[R_AZ], gel = g[R_EL], ca = g[R_CA], cb = g[R_CB], cc = g[R_CC];
  const S* az = tr.az.data();
  const S* el = tr.el.data();
  const int64_t P = int64_t(tr.az.size());
  for (int64_t k = 0; k < P; ++k) {
    const S dx = azimuth_offset(az[k], gaz);
    const S de = el[k] - gel;
    pw[k] = S(-0.5) * (ca * dx * dx + cc * de * de) - cb * dx * de;
  }
}

// One pair past the exponent: its values, or false when it is skipped (alpha below 1/255,
// range undefined or outside the limits). The forward and the backward both call it.
template <typename S>
struct Pair {
  S G, raw, a, den, r;
};

template <typename S>
inline bool evaluate(const S* g, S power, const S* u, S rmin, S rmax, Pair<S>& p) {
  if (power < g[R_FLOOR] || power > S(0)) return false;  // below the floor alpha < 1/255 for sure
  p.G = std::exp(power);
  p.raw = g[R_OP] * p.G;
  p.a = std::min(S(ALPHA_MAX), p.raw);
  if (p.a < S(ALPHA_MIN)) return false;
  const S* q = g + R_Q;
  p.den = q[0] * u[0] * u[0] + q[3] * u[1] * u[1] + q[5] * u[2] * u[2] +
          S(2) * (q[1] * u[0] * u[1] + q[2] * u[0] * u[2] + q[4] * u[1] * u[2]);
  if (!(p.den > S(MIN_DEN))) return false;  // range undefined or meaningless (lidarprojection.py)
  p.r = (g[R_L] * u[0] + g[R_L + 1] * u[1] + g[R_L + 2] * u[2]) / p.den;
  return p.r >= rmin && p.r <= rmax;
}

template <typename S>
void pack_records(int64_t N, const S* az, const S* el, const S* con, const S* op, const S* quad, const S* lin,
                  S* rec, int nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t i = 0; i < N; ++i) {
    S* g = rec + i * REC;
    g[R_AZ] = az[i];
    g[R_EL] = el[i];
    g[R_CA] = con[3 * i];
    g[R_CB] = con[3 * i + 1];
    g[R_CC] = con[3 * i + 2];
    g[R_OP] = op[i];
    // alpha = o exp(power) < 1/255 below ln(1 / (255 o)), less a margin for the exp's rounding
    g[R_FLOOR] = op[i] > S(0) ? S(std::log(ALPHA_MIN / double(op[i])) - 0.01) : S(1);
    for (int k = 0; k < 6; ++k) g[R_Q + k] = quad[6 * i + k];
    for (int k = 0; k < 3; ++k) g[R_L + k] = lin[3 * i + k];
  }
}

// Per tile: its rays' state (transmittance, sums, whether still composited), then each
// Gaussian of the list in order against every live ray of the tile. With ``probe`` (R,)
// (else null) also the transmittance left by the pairs in front of each ray's probe range.
template <typename S>
void composite_forward(const Lists& gl, const Lists& rl, const S* rec, const S* feat, int F, const S* ray_az,
                       const S* ray_el, const S* dirs, S rmin, S rmax, const S* probe, S* out_feat, S* out_rsum,
                       S* out_alpha, S* out_median, S* out_probe, int nthreads) {
  const int64_t tiles = gl.off.size(0) - 1;
  const int64_t* goff = gl.off.data_ptr<int64_t>();
  const int32_t* gids = gl.items.data_ptr<int32_t>();
#pragma omp parallel num_threads(nthreads)
  {
    TileWalk<S> ws;
    std::vector<S> rsum, median, acc, light, at;
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < tiles; ++tile) {
      const int64_t P = ws.start(rl, tile, ray_az, ray_el, dirs);
      if (P == 0) continue;
      rsum.assign(P, S(0));
      median.assign(P, rmax);
      acc.assign(P * F, S(0));
      if (probe) {
        light.assign(P, S(1));
        at.resize(P);
        for (int64_t k = 0; k < P; ++k) at[k] = probe[ws.id[k]];
      }
      for (int64_t e = goff[tile]; e < goff[tile + 1] && ws.live > 0; ++e) {
        const int64_t gi = gids[e];
        const S* g = rec + gi * REC;
        powers(g, ws, ws.pw.data());
        const S* f = feat + gi * F;
        Pair<S> p;
        for (int64_t k = 0; k < P; ++k) {
          if (!ws.alive[k] || !evaluate(g, ws.pw[k], &ws.u[3 * k], rmin, rmax, p)) continue;
          const S nT = ws.T[k] * (S(1) - p.a);
          if (nT <= S(T_MIN)) {  // keep only while the transmittance stays above 1e-4
            ws.alive[k] = 0;
            --ws.live;
            continue;
          }
          const S w = p.a * ws.T[k];
          for (int c = 0; c < F; ++c) acc[k * F + c] += w * f[c];
          rsum[k] += w * p.r;
          if (!ws.crossed[k] && nT <= S(0.5)) {  // T was above 0.5 (it only falls by composited pairs)
            median[k] = p.r;
            ws.crossed[k] = 1;
          }
          if (probe && p.r < at[k]) light[k] *= S(1) - p.a;
          ws.T[k] = nT;
        }
      }
      for (int64_t k = 0; k < P; ++k) {
        const int64_t j = ws.id[k];
        for (int c = 0; c < F; ++c) out_feat[j * F + c] = acc[k * F + c];
        out_rsum[j] = rsum[k];
        out_alpha[j] = S(1) - ws.T[k];
        out_median[j] = median[k];
        if (probe) out_probe[j] = light[k];
      }
    }
  }
}

// The forward's walk again with the gradients: dL/dalpha_i = T_i c_i - (sum over later
// pairs of w_j c_j) / (1 - alpha_i), the later sum being the total (from the forward's
// outputs) less the running prefix; a pair in front of the ray's probe adds
// -g_probe T_probe / (1 - alpha_i). Per Gaussian the sums over the tile's rays go to a
// per-thread buffer; the buffers are added in thread order.
template <typename S>
void composite_backward(const Lists& gl, const Lists& rl, const S* rec, const S* feat, int F, const S* ray_az,
                        const S* ray_el, const S* dirs, S rmin, S rmax, const S* o_feat, const S* o_rsum,
                        const S* o_alpha, const S* g_feat, const S* g_rsum, const S* g_alpha, const S* g_median,
                        const S* probe, const S* o_probe, const S* g_probe, int64_t N, double* grads,
                        int nthreads) {
  const int64_t tiles = gl.off.size(0) - 1;
  const int64_t* goff = gl.off.data_ptr<int64_t>();
  const int32_t* gids = gl.items.data_ptr<int32_t>();
  const int K = G_F + F;
  std::vector<double> buffers(size_t(nthreads > 1 ? nthreads - 1 : 0) * N * K, 0.0);
#pragma omp parallel num_threads(nthreads)
  {
    const int me = omp_get_thread_num();
    double* mine = me == 0 ? grads : buffers.data() + size_t(me - 1) * N * K;  // thread 0 writes the output
    TileWalk<S> ws;
    std::vector<S> prefix, total, gf, gR, gA, gM, at, gP;
    std::vector<double> d(K);
#pragma omp for schedule(static, 1)
    for (int64_t tile = 0; tile < tiles; ++tile) {
      const int64_t P = ws.start(rl, tile, ray_az, ray_el, dirs);
      if (P == 0) continue;
      prefix.assign(P, S(0));
      total.resize(P);
      gf.resize(P * F);
      gR.resize(P);
      gA.resize(P);
      gM.resize(P);
      if (probe) {
        at.resize(P);
        gP.resize(P);
      }
      for (int64_t k = 0; k < P; ++k) {
        const int64_t j = ws.id[k];
        if (probe) {
          at[k] = probe[j];
          gP[k] = g_probe[j] * o_probe[j];  // dL/dT_probe * T_probe
        }
        gR[k] = g_rsum[j];
        gA[k] = g_alpha[j];
        gM[k] = g_median[j];
        // total = sum_i w_i c_i with c_i = gf . f_i + gR r_i + gA, from the forward's outputs
        S t = gR[k] * o_rsum[j] + gA[k] * o_alpha[j];
        for (int c = 0; c < F; ++c) {
          gf[k * F + c] = g_feat[j * F + c];
          t += gf[k * F + c] * o_feat[j * F + c];
        }
        total[k] = t;
      }
      for (int64_t e = goff[tile]; e < goff[tile + 1] && ws.live > 0; ++e) {
        const int64_t gi = gids[e];
        const S* g = rec + gi * REC;
        powers(g, ws, ws.pw.data());
        const S* f = feat + gi * F;
        std::fill(d.begin(), d.end(), 0.0);
        bool touched = false;
        Pair<S> p;
        for (int64_t k = 0; k < P; ++k) {
          if (!ws.alive[k] || !evaluate(g, ws.pw[k], &ws.u[3 * k], rmin, rmax, p)) continue;
          const S nT = ws.T[k] * (S(1) - p.a);
          if (nT <= S(T_MIN)) {
            ws.alive[k] = 0;
            --ws.live;
            continue;
          }
          touched = true;
          const S w = p.a * ws.T[k];
          const S* gfk = &gf[k * F];
          S ci = gA[k] + gR[k] * p.r;
          for (int c = 0; c < F; ++c) {
            ci += gfk[c] * f[c];
            d[G_F + c] += double(w * gfk[c]);
          }
          prefix[k] += w * ci;
          const S suffix = total[k] - prefix[k];  // sum over the later pairs of w_j c_j
          S dal = ws.T[k] * ci - suffix / (S(1) - p.a);
          if (probe && p.r < at[k]) dal -= gP[k] / (S(1) - p.a);
          S dr = w * gR[k];
          if (!ws.crossed[k] && nT <= S(0.5)) {
            dr += gM[k];
            ws.crossed[k] = 1;
          }
          if (p.raw < S(ALPHA_MAX)) {  // alpha clamped at 0.99: no gradient to opacity or power
            const S dx = azimuth_offset(ws.az[k], g[R_AZ]);
            const S de = ws.el[k] - g[R_EL];
            const S dpow = dal * p.a;
            d[G_OP] += double(dal * p.G);
            d[G_CA] += double(S(-0.5) * dpow * dx * dx);
            d[G_CB] += double(-dpow * dx * de);
            d[G_CC] += double(S(-0.5) * dpow * de * de);
            // dx = ray azimuth - Gaussian azimuth: d power / d azimuth = ca dx + cb de
            d[G_AZ] += double(dpow * (g[R_CA] * dx + g[R_CB] * de));
            d[G_EL] += double(dpow * (g[R_CB] * dx + g[R_CC] * de));
          }
          const S* u = &ws.u[3 * k];
          const S dnum = dr / p.den, dden = -dr * p.r / p.den;  // r = num / den
          for (int c = 0; c < 3; ++c) d[G_L + c] += double(dnum * u[c]);
          d[G_Q + 0] += double(dden * u[0] * u[0]);
          d[G_Q + 1] += double(dden * S(2) * u[0] * u[1]);
          d[G_Q + 2] += double(dden * S(2) * u[0] * u[2]);
          d[G_Q + 3] += double(dden * u[1] * u[1]);
          d[G_Q + 4] += double(dden * S(2) * u[1] * u[2]);
          d[G_Q + 5] += double(dden * u[2] * u[2]);
          ws.T[k] = nT;
        }
        if (touched) {
          double* dst = mine + gi * K;
          for (int c = 0; c < K; ++c) dst[c] += d[c];
        }
      }
    }
  }
  // the other threads' sums, in thread order (repeatable for a given thread count)
  for (int t = 0; t + 1 < nthreads; ++t) {
    const double* b = buffers.data() + size_t(t) * N * K;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t i = 0; i < N * K; ++i) grads[i] += b[i];
  }
}

// ---------------------------------------------------------------------------------------
// Projection to the sensor's sphere (the numbers of omnire/lidarprojection.py, computed in
// double) and its backward to means, quaternions and scales.

constexpr double DEG = 180.0 / 3.14159265358979323846;
constexpr double POLE_SIN = 0.017452406437283512;  // sin(1 degree): POLE_MARGIN_DEG
constexpr double MIN_SCALE = 1e-12;                  // lidarprojection.py MIN_SCALE
constexpr double QUAT_EPS2 = 1e-24;                  // omnire.geometry.normalize_quats

// Forward-mode value with its derivatives along the three sensor axes: J(m)'s derivative.
struct Dual3 {
  double v, d[3];
};
inline Dual3 operator+(Dual3 a, Dual3 b) { return {a.v + b.v, {a.d[0] + b.d[0], a.d[1] + b.d[1], a.d[2] + b.d[2]}}; }
inline Dual3 operator*(Dual3 a, Dual3 b) {
  return {a.v * b.v, {a.d[0] * b.v + a.v * b.d[0], a.d[1] * b.v + a.v * b.d[1], a.d[2] * b.v + a.v * b.d[2]}};
}
inline Dual3 operator*(double s, Dual3 a) { return {s * a.v, {s * a.d[0], s * a.d[1], s * a.d[2]}}; }
inline Dual3 operator/(Dual3 a, Dual3 b) {
  const double q = a.v / b.v;
  return {q, {(a.d[0] - q * b.d[0]) / b.v, (a.d[1] - q * b.d[1]) / b.v, (a.d[2] - q * b.d[2]) / b.v}};
}
inline Dual3 sqrt(Dual3 a) {
  const double r = std::sqrt(a.v);
  return {r, {a.d[0] / (2 * r), a.d[1] / (2 * r), a.d[2] / (2 * r)}};
}
using std::sqrt;

// Jacobian (2, 3) of (azimuth, elevation) in degrees at the sensor-frame point m, row-major.
template <typename T>
inline void spherical_jacobian(const T m[3], T J[6]) {
  const T x = m[0], y = m[1], z = m[2];
  const T r2 = x * x + y * y;
  const T R2 = r2 + z * z;
  const T r = sqrt(r2);
  const T Rr = R2 * r;
  J[0] = (-DEG) * (y / r2);
  J[1] = DEG * (x / r2);
  J[2] = 0.0 * x;
  J[3] = (-DEG) * (x * z / Rr);
  J[4] = (-DEG) * (y * z / Rr);
  J[5] = DEG * (r / R2);
}

// Everything the forward computes for one Gaussian, kept for its backward.
struct Proj {
  double m[3], qn[4], qnorm, rot[9], J[6], JM[6], a, b, c, det, sp[3], w[3], Q[9];
  int smin;  // first index of the smallest clamped scale
  bool visible, ok, unit;
};

inline void quat_rotmat(const double q[4], double R[9]) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z); R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z); R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y); R[7] = 2 * (y * z + w * x); R[8] = 1 - 2 * (x * x + y * y);
}

// pose: (4, 4) sensor_to_world, row-major doubles.
template <typename S>
inline void project_one(const S* mean, const S* quat, const S* scale, double opac, const double* pose, double eps,
                        double rmin, double rmax, Proj& p) {
  for (int i = 0; i < 3; ++i) {  // m = Rs^T (mu - t)
    p.m[i] = 0;
    for (int k = 0; k < 3; ++k) p.m[i] += pose[4 * k + i] * (double(mean[k]) - pose[4 * k + 3]);
  }
  const double x = p.m[0], y = p.m[1], z = p.m[2];
  const double r2 = x * x + y * y, rho = std::sqrt(r2 + z * z), r = std::sqrt(r2);
  p.visible = rho > rmin && rho < rmax && r > rho * POLE_SIN && opac >= ALPHA_MIN;
  double norm2 = 0;
  for (int k = 0; k < 4; ++k) norm2 += double(quat[k]) * double(quat[k]);
  p.unit = norm2 >= QUAT_EPS2;
  p.qnorm = p.unit ? std::sqrt(norm2) : 1.0;
  for (int k = 0; k < 4; ++k) p.qn[k] = p.unit ? double(quat[k]) / p.qnorm : (k == 0 ? 1.0 : 0.0);
  double Rq[9];
  quat_rotmat(p.qn, Rq);
  for (int i = 0; i < 3; ++i)  // rot = Rs^T Rq
    for (int j = 0; j < 3; ++j) {
      double v = 0;
      for (int k = 0; k < 3; ++k) v += pose[4 * k + i] * Rq[3 * k + j];
      p.rot[3 * i + j] = v;
    }
  const double stand_in[3] = {1.0, 0.0, 0.0};  // undrawn Gaussians: a harmless point (as the torch code)
  spherical_jacobian(p.visible ? p.m : stand_in, p.J);
  for (int a = 0; a < 2; ++a)  // JM = J rot diag(s)
    for (int j = 0; j < 3; ++j) {
      double v = 0;
      for (int i = 0; i < 3; ++i) v += p.J[3 * a + i] * p.rot[3 * i + j];
      p.JM[3 * a + j] = v * double(scale[j]);
    }
  p.a = p.JM[0] * p.JM[0] + p.JM[1] * p.JM[1] + p.JM[2] * p.JM[2] + eps;
  p.b = p.JM[0] * p.JM[3] + p.JM[1] * p.JM[4] + p.JM[2] * p.JM[5];
  p.c = p.JM[3] * p.JM[3] + p.JM[4] * p.JM[4] + p.JM[5] * p.JM[5] + eps;
  p.det = p.a * p.c - p.b * p.b;
  p.ok = p.visible && p.det > 0;
  p.smin = 0;
  for (int k = 0; k < 3; ++k) {
    p.sp[k] = std::max(double(scale[k]), MIN_SCALE);
    if (p.sp[k] < p.sp[p.smin]) p.smin = k;
  }
  for (int k = 0; k < 3; ++k) {
    const double t = p.sp[p.smin] / p.sp[k];
    p.w[k] = t * t;
  }
  for (int i = 0; i < 3; ++i)  // Q = rot diag(w) rot^T
    for (int j = 0; j < 3; ++j) {
      double v = 0;
      for (int k = 0; k < 3; ++k) v += p.rot[3 * i + k] * p.w[k] * p.rot[3 * j + k];
      p.Q[3 * i + j] = v;
    }
}

template <typename S>
void project_all(int64_t N, const S* means, const S* quats, const S* scales, const S* opac, const double* pose,
                 double eps, double rmin, double rmax, S* az, S* el, S* conics, S* quad, S* lin, S* distance,
                 S* extent, bool* visible, int nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t i = 0; i < N; ++i) {
    Proj p;
    project_one(means + 3 * i, quats + 4 * i, scales + 3 * i, double(opac[i]), pose, eps, rmin, rmax, p);
    const double* m = p.visible ? p.m : nullptr;
    const double x = m ? m[0] : 1.0, y = m ? m[1] : 0.0, z = m ? m[2] : 0.0;
    const double r = std::sqrt(x * x + y * y);
    double a = DEG * std::atan2(y, x);
    if (a < 0) a += 360.0;
    az[i] = S(a);
    el[i] = S(DEG * std::atan2(z, r));
    const double det = p.ok ? p.det : 1.0;
    conics[3 * i] = S(p.c / det);
    conics[3 * i + 1] = S(-p.b / det);
    conics[3 * i + 2] = S(p.a / det);
    const int upper[6] = {0, 1, 2, 4, 5, 8};
    for (int k = 0; k < 6; ++k) quad[6 * i + k] = S(p.Q[upper[k]]);
    for (int k = 0; k < 3; ++k) lin[3 * i + k] = S(p.Q[3 * k] * x + p.Q[3 * k + 1] * y + p.Q[3 * k + 2] * z);
    distance[i] = S(std::sqrt(x * x + y * y + z * z));
    const double level = 2.0 * std::log(std::max(double(opac[i]) / ALPHA_MIN, 1.0));
    for (int k = 0; k < 2; ++k) {
      double e = 1.01 * std::sqrt(level * std::max(k == 0 ? p.a : p.c, 0.0)) + 1e-3;  // EXTENT_MARGIN
      if (!std::isfinite(e) || e > 360.0) e = 360.0;
      extent[2 * i + k] = S(p.ok ? e : 0.0);
    }
    visible[i] = p.ok;
  }
}

template <typename S>
void project_backward_all(int64_t N, const S* means, const S* quats, const S* scales, const S* opac,
                          const double* pose, double eps, double rmin, double rmax, const S* g_az, const S* g_el,
                          const S* g_con, const S* g_quad, const S* g_lin, S* g_means, S* g_quats, S* g_scales,
                          int nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t i = 0; i < N; ++i) {
    Proj p;
    project_one(means + 3 * i, quats + 4 * i, scales + 3 * i, double(opac[i]), pose, eps, rmin, rmax, p);
    double gm[3] = {0, 0, 0}, grot[9] = {0}, gs[3] = {0, 0, 0};
    if (p.visible) {
      // conic = (c, -b, a) / det
      double ga = 0, gb = 0, gc = 0;
      if (p.ok) {
        const double g0 = g_con[3 * i], g1 = g_con[3 * i + 1], g2 = g_con[3 * i + 2];
        const double id = 1.0 / p.det, id2 = id * id, a = p.a, b = p.b, c = p.c;
        ga = -g0 * c * c * id2 + g1 * b * c * id2 + g2 * (id - a * c * id2);
        gb = 2 * g0 * b * c * id2 + g1 * (-id - 2 * b * b * id2) + 2 * g2 * a * b * id2;
        gc = g0 * (id - a * c * id2) + g1 * a * b * id2 - g2 * a * a * id2;
      } else {  // det held at 1: conic = (c, -b, a)
        ga = g_con[3 * i + 2];
        gb = -double(g_con[3 * i + 1]);
        gc = g_con[3 * i];
      }
      // cov = JM JM^T (a, b, c its upper entries)
      double gJM[6];
      for (int j = 0; j < 3; ++j) {
        gJM[j] = 2 * ga * p.JM[j] + gb * p.JM[3 + j];
        gJM[3 + j] = gb * p.JM[j] + 2 * gc * p.JM[3 + j];
      }
      // JM = J rot diag(s)
      double gJ[6] = {0};
      for (int a = 0; a < 2; ++a)
        for (int j = 0; j < 3; ++j) {
          const double gmj = gJM[3 * a + j];
          double jr = 0;
          for (int k = 0; k < 3; ++k) {
            gJ[3 * a + k] += gmj * double(scales[3 * i + j]) * p.rot[3 * k + j];
            grot[3 * k + j] += p.J[3 * a + k] * gmj * double(scales[3 * i + j]);
            jr += p.J[3 * a + k] * p.rot[3 * k + j];
          }
          gs[j] += gmj * jr;
        }
      // J(m) and (azimuth, elevation)(m), whose Jacobian is J itself
      Dual3 md[3];
      for (int k = 0; k < 3; ++k) md[k] = {p.m[k], {k == 0 ? 1.0 : 0.0, k == 1 ? 1.0 : 0.0, k == 2 ? 1.0 : 0.0}};
      Dual3 Jd[6];
      spherical_jacobian(md, Jd);
      for (int k = 0; k < 3; ++k) {
        gm[k] += double(g_az[i]) * p.J[k] + double(g_el[i]) * p.J[3 + k];
        for (int e = 0; e < 6; ++e) gm[k] += gJ[e] * Jd[e].d[k];
      }
    }
    // lin = Q m and quad = Q's upper entries; Q = rot diag(w) rot^T, w = (s_min / s)^2
    const double* mm = p.visible ? p.m : nullptr;
    const double mx[3] = {mm ? mm[0] : 1.0, mm ? mm[1] : 0.0, mm ? mm[2] : 0.0};
    double gQ[9];
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) gQ[3 * r + c] = double(g_lin[3 * i + r]) * mx[c];
    const int upper[6] = {0, 1, 2, 4, 5, 8};
    for (int k = 0; k < 6; ++k) gQ[upper[k]] += double(g_quad[6 * i + k]);
    if (p.visible)
      for (int k = 0; k < 3; ++k)
        for (int r = 0; r < 3; ++r) gm[k] += double(g_lin[3 * i + r]) * p.Q[3 * r + k];
    double gw[3] = {0, 0, 0};
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 3; ++k) {
        double sym = 0;  // ((gQ + gQ^T) rot)_rk
        for (int j = 0; j < 3; ++j) sym += (gQ[3 * r + j] + gQ[3 * j + r]) * p.rot[3 * j + k];
        grot[3 * r + k] += sym * p.w[k];
        for (int j = 0; j < 3; ++j) gw[k] += gQ[3 * r + j] * p.rot[3 * r + k] * p.rot[3 * j + k];
      }
    double gsp[3] = {0, 0, 0}, gmin = 0;
    for (int k = 0; k < 3; ++k) {
      gsp[k] += gw[k] * (-2.0 * p.w[k] / p.sp[k]);
      gmin += gw[k] * 2.0 * p.w[k] / p.sp[p.smin];
    }
    gsp[p.smin] += gmin;
    for (int k = 0; k < 3; ++k)
      if (double(scales[3 * i + k]) >= MIN_SCALE) gs[k] += gsp[k];
    // rot = Rs^T Rq, Rq = R(qn), qn = q / |q|
    double gR[9];
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) {
        double v = 0;
        for (int k = 0; k < 3; ++k) v += pose[4 * r + k] * grot[3 * k + c];
        gR[3 * r + c] = v;
      }
    const double w = p.qn[0], x = p.qn[1], y = p.qn[2], z = p.qn[3];
    const double gqn[4] = {
        2 * (-z * gR[1] + y * gR[2] + z * gR[3] - x * gR[5] - y * gR[6] + x * gR[7]),
        2 * (y * gR[1] + z * gR[2] + y * gR[3] - 2 * x * gR[4] - w * gR[5] + z * gR[6] + w * gR[7] - 2 * x * gR[8]),
        2 * (-2 * y * gR[0] + x * gR[1] + w * gR[2] + x * gR[3] + z * gR[5] - w * gR[6] + z * gR[7] - 2 * y * gR[8]),
        2 * (-2 * z * gR[0] - w * gR[1] + x * gR[2] + w * gR[3] - 2 * z * gR[4] + y * gR[5] + x * gR[6] + y * gR[7])};
    const double dot = w * gqn[0] + x * gqn[1] + y * gqn[2] + z * gqn[3];
    for (int k = 0; k < 4; ++k) g_quats[4 * i + k] = S(p.unit ? (gqn[k] - p.qn[k] * dot) / p.qnorm : 0.0);
    for (int k = 0; k < 3; ++k) {  // m = Rs^T (mu - t): dL/dmu = Rs dL/dm
      g_means[3 * i + k] = S(pose[4 * k] * gm[0] + pose[4 * k + 1] * gm[1] + pose[4 * k + 2] * gm[2]);
      g_scales[3 * i + k] = S(gs[k]);
    }
  }
}


// The tiling of omnire.lidarprojection.SphereTiles: ``columns`` of ``column_deg`` from
// azimuth 0, ``rows`` of ``row_deg`` from ``first`` (its of_rays and boxes, in double).
struct Tiling {
  int64_t columns, rows;
  double column_deg, row_deg, first;
  int64_t count() const { return columns * rows; }
};

// Rays: azimuth taken into [0, 360) (S), direction (S, (R, 3)), tile (R,).
template <typename S>
void prepare_rays(int64_t R, const S* az_in, const S* el_in, const Tiling& t, S* az, S* dirs, int64_t* tile,
                  int nthreads) {
  constexpr double RAD = 3.14159265358979323846 / 180.0;
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t j = 0; j < R; ++j) {
    double a = std::fmod(double(az_in[j]), 360.0);
    if (a < 0) a += 360.0;
    const double e = double(el_in[j]);
    az[j] = S(a);
    const double ar = double(az_in[j]) * RAD, er = e * RAD;
    dirs[3 * j] = S(std::cos(er) * std::cos(ar));
    dirs[3 * j + 1] = S(std::cos(er) * std::sin(ar));
    dirs[3 * j + 2] = S(std::sin(er));
    const int64_t col = std::min(std::max(int64_t(std::floor(a / t.column_deg)), int64_t(0)), t.columns - 1);
    const int64_t row = std::min(std::max(int64_t(std::floor((e - t.first) / t.row_deg)), int64_t(0)), t.rows - 1);
    tile[j] = row * t.columns + col;
  }
}

// Tile box of each Gaussian (first column, columns, first row, rows; rows 0 when not drawn).
template <typename S>
void tile_boxes(int64_t N, const S* az, const S* el, const S* extent, const bool* visible, const Tiling& t,
                int64_t* box, int nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t i = 0; i < N; ++i) {
    const double a = az[i], e = el[i], ea = extent[2 * i], ee = extent[2 * i + 1];
    const int64_t c0 = int64_t(std::floor((a - ea) / t.column_deg));
    const int64_t c1 = int64_t(std::floor((a + ea) / t.column_deg));
    const int64_t r0 = std::max(int64_t(std::floor((e - ee - t.first) / t.row_deg)), int64_t(0));
    const int64_t r1 = std::min(int64_t(std::floor((e + ee - t.first) / t.row_deg)), t.rows - 1);
    int64_t* b = box + 4 * i;
    b[0] = ((c0 % t.columns) + t.columns) % t.columns;
    b[1] = std::min(c1 - c0 + 1, t.columns);
    b[2] = std::min(r0, t.rows);
    b[3] = visible[i] ? std::max(r1 - r0 + 1, int64_t(0)) : 0;
  }
}

}  // namespace

// Forward. Inputs (S = float32 or float64, N Gaussians, F features, R rays): the outputs of
// lidar_project (azimuth, elevation (N,), conics (N,3), quad (N,6), lin (N,3), distance
// (N,), extent (N,2), visible (N,) bool), opacities (N,), features (N,F); the rays' azimuth
// and elevation (R,) in degrees; the tiling (columns, rows, column_deg, row_deg, first
// elevation); min_range, max_range; the probe ranges (R,), or (0,) for none.
// Returns [features (R,F), range sum (R,), alpha (R,), median range (R,), records (N,REC),
//          Gaussian tile offsets, Gaussian ids, ray tile offsets, ray ids, ray azimuths in
//          [0, 360) (R,), ray directions (R,3), transmittance at the probes (R,) or (0,)].
std::vector<at::Tensor> lidar_forward(at::Tensor az, at::Tensor el, at::Tensor opac, at::Tensor conics,
                                      at::Tensor quad, at::Tensor lin, at::Tensor feat, at::Tensor distance,
                                      at::Tensor extent, at::Tensor visible, at::Tensor ray_az_in, at::Tensor ray_el,
                                      int64_t columns, int64_t rows, double column_deg, double row_deg,
                                      double first_elevation, double min_range, double max_range,
                                      at::Tensor probe, int64_t nthreads) {
  const auto st = az.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "azimuth must be float32 or float64");
  const int64_t N = az.size(0), R = ray_az_in.size(0), F = feat.dim() == 2 ? feat.size(1) : 0;
  TORCH_CHECK(F >= 1, "features must be (N, F) with F >= 1");
  TORCH_CHECK(columns >= 1 && rows >= 1 && column_deg > 0 && row_deg > 0, "bad tiling");
  check(az, st, "azimuth", N, -1);
  check(el, st, "elevation", N, -1);
  check(opac, st, "opacities", N, -1);
  check(conics, st, "conics", N, 3);
  check(quad, st, "quad", N, 6);
  check(lin, st, "lin", N, 3);
  check(feat, st, "features", N, F);
  check(distance, st, "distance", N, -1);
  check(extent, st, "extent", N, 2);
  check(visible, at::kBool, "visible", N, -1);
  check(ray_az_in, st, "ray_azimuth", R, -1);
  check(ray_el, st, "ray_elevation", R, -1);
  const bool probed = probe.numel() > 0;
  if (probed) check(probe, st, "probe_range", R, -1);
  TORCH_CHECK(N < (int64_t(1) << 31), "too many Gaussians for int32 ids");
  const int nt = int(std::max<int64_t>(1, nthreads));
  const Tiling tiling{columns, rows, column_deg, row_deg, first_elevation};
  auto opts = az.options();
  at::Tensor ray_az = at::empty({R}, opts), dirs = at::empty({R, 3}, opts);
  at::Tensor ray_tile = at::empty({R}, at::kLong), box = at::empty({N, 4}, at::kLong);
  at::Tensor rec = at::empty({N, REC}, opts), o_feat = at::empty({R, F}, opts), o_rsum = at::empty({R}, opts);
  at::Tensor o_alpha = at::empty({R}, opts), o_median = at::empty({R}, opts);
  at::Tensor o_probe = at::empty({probed ? R : 0}, opts);
  Lists gl, rl;
  AT_DISPATCH_FLOATING_TYPES(st, "lidar_forward", [&] {
    prepare_rays<scalar_t>(R, ray_az_in.data_ptr<scalar_t>(), ray_el.data_ptr<scalar_t>(), tiling,
                           ray_az.data_ptr<scalar_t>(), dirs.data_ptr<scalar_t>(), ray_tile.data_ptr<int64_t>(), nt);
    tile_boxes<scalar_t>(N, az.data_ptr<scalar_t>(), el.data_ptr<scalar_t>(), extent.data_ptr<scalar_t>(),
                         visible.data_ptr<bool>(), tiling, box.data_ptr<int64_t>(), nt);
    // the drawn Gaussians by centre distance (stable: equal distances in index order)
    const scalar_t* d = distance.data_ptr<scalar_t>();
    const bool* v = visible.data_ptr<bool>();
    std::vector<int64_t> order;
    order.reserve(N);
    for (int64_t i = 0; i < N; ++i)
      if (v[i]) order.push_back(i);
    std::stable_sort(order.begin(), order.end(), [d](int64_t x, int64_t y) { return d[x] < d[y]; });
    gl = bin_gaussians(order.data(), int64_t(order.size()), box.data_ptr<int64_t>(), columns, tiling.count());
    rl = bin_rays(ray_tile.data_ptr<int64_t>(), R, tiling.count());
    pack_records<scalar_t>(N, az.data_ptr<scalar_t>(), el.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           opac.data_ptr<scalar_t>(), quad.data_ptr<scalar_t>(), lin.data_ptr<scalar_t>(),
                           rec.data_ptr<scalar_t>(), nt);
    composite_forward<scalar_t>(gl, rl, rec.data_ptr<scalar_t>(), feat.data_ptr<scalar_t>(), int(F),
                                ray_az.data_ptr<scalar_t>(), ray_el.data_ptr<scalar_t>(), dirs.data_ptr<scalar_t>(),
                                scalar_t(min_range), scalar_t(max_range),
                                probed ? probe.data_ptr<scalar_t>() : nullptr, o_feat.data_ptr<scalar_t>(),
                                o_rsum.data_ptr<scalar_t>(), o_alpha.data_ptr<scalar_t>(),
                                o_median.data_ptr<scalar_t>(), probed ? o_probe.data_ptr<scalar_t>() : nullptr, nt);
  });
  return {o_feat, o_rsum, o_alpha, o_median, rec, gl.off, gl.items, rl.off, rl.items, ray_az, dirs, o_probe};
}

// Backward: dL/d(features, range sum, alpha, median range, transmittance at the probes) per
// ray -> (N, G_F + F) float64 per-Gaussian gradients: azimuth, elevation, conic a b c,
// opacity, quad (6), lin (3), features (F). probe, o_probe, g_probe: (R,) each, or (0,) for none.
at::Tensor lidar_backward(at::Tensor rec, at::Tensor feat, at::Tensor goff, at::Tensor gids, at::Tensor roff,
                          at::Tensor rids, at::Tensor ray_az, at::Tensor ray_el, at::Tensor dirs, at::Tensor o_feat,
                          at::Tensor o_rsum, at::Tensor o_alpha, at::Tensor g_feat, at::Tensor g_rsum,
                          at::Tensor g_alpha, at::Tensor g_median, double min_range, double max_range,
                          at::Tensor probe, at::Tensor o_probe, at::Tensor g_probe, int64_t nthreads) {
  const auto st = rec.scalar_type();
  const int64_t N = rec.size(0), R = ray_az.size(0), F = feat.size(1);
  check(rec, st, "records", N, REC);
  check(feat, st, "features", N, F);
  for (auto [t, name] : {std::pair{&o_feat, "output features"}, {&g_feat, "feature gradient"}})
    check(*t, st, name, R, F);
  for (auto [t, name] : {std::pair{&o_rsum, "range sum"}, {&o_alpha, "alpha"}, {&g_rsum, "range sum gradient"},
                         {&g_alpha, "alpha gradient"}, {&g_median, "median gradient"}, {&ray_az, "ray_azimuth"},
                         {&ray_el, "ray_elevation"}})
    check(*t, st, name, R, -1);
  check(dirs, st, "directions", R, 3);
  const bool probed = probe.numel() > 0;
  if (probed)
    for (auto [t, name] : {std::pair{&probe, "probe_range"}, {&o_probe, "probe transmittance"},
                           {&g_probe, "probe gradient"}})
      check(*t, st, name, R, -1);
  const int nt = int(std::max<int64_t>(1, nthreads));
  at::Tensor grads = at::zeros({N, G_F + F}, at::kDouble);
  Lists gl{goff, gids}, rl{roff, rids};
  AT_DISPATCH_FLOATING_TYPES(st, "lidar_backward", [&] {
    composite_backward<scalar_t>(gl, rl, rec.data_ptr<scalar_t>(), feat.data_ptr<scalar_t>(), int(F),
                                 ray_az.data_ptr<scalar_t>(), ray_el.data_ptr<scalar_t>(), dirs.data_ptr<scalar_t>(),
                                 scalar_t(min_range), scalar_t(max_range), o_feat.data_ptr<scalar_t>(),
                                 o_rsum.data_ptr<scalar_t>(), o_alpha.data_ptr<scalar_t>(),
                                 g_feat.data_ptr<scalar_t>(), g_rsum.data_ptr<scalar_t>(),
                                 g_alpha.data_ptr<scalar_t>(), g_median.data_ptr<scalar_t>(),
                                 probed ? probe.data_ptr<scalar_t>() : nullptr,
                                 probed ? o_probe.data_ptr<scalar_t>() : nullptr,
                                 probed ? g_probe.data_ptr<scalar_t>() : nullptr, N, grads.data_ptr<double>(), nt);
  });
  return grads;
}

// The inputs of the projection: float32 or float64 Gaussians, a float64 pose. Returns N.
static int64_t check_gaussians(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                               const at::Tensor& opac, const at::Tensor& pose) {
  const auto st = means.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "means must be float32 or float64");
  const int64_t N = means.size(0);
  check(means, st, "means", N, 3);
  check(quats, st, "quats", N, 4);
  check(scales, st, "scales", N, 3);
  check(opac, st, "opacities", N, -1);
  check(pose, at::kDouble, "pose", 4, 4);
  return N;
}

// Projection of N Gaussians (means (N,3), quats (N,4), scales (N,3), opacities (N,), all S)
// to the sphere of the sensor at ``pose`` (4,4) float64. Returns [azimuth, elevation (N,),
// conics (N,3), quad (N,6), lin (N,3), distance (N,), extent (N,2), visible (N,) bool], the
// quantities of omnire/lidarprojection.py's SphericalSplats (computed in double).
std::vector<at::Tensor> lidar_project(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opac,
                                      at::Tensor pose, double eps, double min_range, double max_range,
                                      int64_t nthreads) {
  const auto st = means.scalar_type();
  const int64_t N = check_gaussians(means, quats, scales, opac, pose);
  auto opts = means.options();
  at::Tensor az = at::empty({N}, opts), el = at::empty({N}, opts), con = at::empty({N, 3}, opts);
  at::Tensor quad = at::empty({N, 6}, opts), lin = at::empty({N, 3}, opts), dist = at::empty({N}, opts);
  at::Tensor ext = at::empty({N, 2}, opts), vis = at::empty({N}, opts.dtype(at::kBool));
  const int nt = int(std::max<int64_t>(1, nthreads));
  AT_DISPATCH_FLOATING_TYPES(st, "lidar_project", [&] {
    project_all<scalar_t>(N, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
                          opac.data_ptr<scalar_t>(), pose.data_ptr<double>(), eps, min_range, max_range,
                          az.data_ptr<scalar_t>(), el.data_ptr<scalar_t>(), con.data_ptr<scalar_t>(),
                          quad.data_ptr<scalar_t>(), lin.data_ptr<scalar_t>(), dist.data_ptr<scalar_t>(),
                          ext.data_ptr<scalar_t>(), vis.data_ptr<bool>(), nt);
  });
  return {az, el, con, quad, lin, dist, ext, vis};
}

// Backward of lidar_project: dL/d(azimuth, elevation, conics, quad, lin) -> dL/d(means, quats, scales).
std::vector<at::Tensor> lidar_project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opac,
                                               at::Tensor pose, double eps, double min_range, double max_range,
                                               at::Tensor g_az, at::Tensor g_el, at::Tensor g_con, at::Tensor g_quad,
                                               at::Tensor g_lin, int64_t nthreads) {
  const auto st = means.scalar_type();
  const int64_t N = check_gaussians(means, quats, scales, opac, pose);
  check(g_az, st, "azimuth gradient", N, -1);
  check(g_el, st, "elevation gradient", N, -1);
  check(g_con, st, "conics gradient", N, 3);
  check(g_quad, st, "quad gradient", N, 6);
  check(g_lin, st, "lin gradient", N, 3);
  at::Tensor gm = at::empty_like(means), gq = at::empty_like(quats), gs = at::empty_like(scales);
  const int nt = int(std::max<int64_t>(1, nthreads));
  AT_DISPATCH_FLOATING_TYPES(st, "lidar_project_backward", [&] {
    project_backward_all<scalar_t>(N, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                   scales.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(), pose.data_ptr<double>(),
                                   eps, min_range, max_range, g_az.data_ptr<scalar_t>(), g_el.data_ptr<scalar_t>(),
                                   g_con.data_ptr<scalar_t>(), g_quad.data_ptr<scalar_t>(), g_lin.data_ptr<scalar_t>(),
                                   gm.data_ptr<scalar_t>(), gq.data_ptr<scalar_t>(), gs.data_ptr<scalar_t>(), nt);
  });
  return {gm, gq, gs};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("lidar_project", &lidar_project, "projection of Gaussians to the sensor's sphere (CPU)");
  m.def("lidar_project_backward", &lidar_project_backward, "backward of lidar_project (CPU)");
  m.def("lidar_forward", &lidar_forward, "LiDAR compositing forward over tiles of the sphere (CPU)");
  m.def("lidar_backward", &lidar_backward, "LiDAR compositing backward to the projected Gaussians (CPU)");
}
