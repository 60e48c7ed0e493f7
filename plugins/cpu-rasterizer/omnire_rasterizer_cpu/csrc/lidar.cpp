// Native LiDAR compositing for omnire's cpu rasterizer: the ``lidar`` capability of
// omnire/rasterization.py. The Gaussians arrive projected to the sensor's sphere by
// omnire/lidarprojection.py (torch, differentiable): per Gaussian its direction (azimuth,
// elevation, degrees), the inverse angular covariance (conic a, b, c), opacity, the range
// quadric (quad xx xy xz yy yz zz, lin x y z: t* = d.lin / d^T quad d) and its tile box.
// Here: bin Gaussians (in the caller's order of centre distance) and rays into tiles of the
// sphere, composite the rays of each tile over its list (each Gaussian of the list against
// every live ray of the tile, the exponents in a loop the compiler vectorises), and the
// backward of that compositing to the per-Gaussian quantities (torch's autograd takes it
// through the projection). OpenMP over tiles.
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

// The rays of one tile, gathered: azimuth in [0, 360), elevation, direction.
template <typename S>
struct TileRays {
  std::vector<int64_t> id;
  std::vector<S> az, el, u;  // u: (P, 3)
  void load(const Lists& rl, int64_t tile, const S* ray_az, const S* ray_el, const S* dirs) {
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
inline void powers(const S* g, const TileRays<S>& tr, S* pw) {
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
// Gaussian of the list in order against every live ray of the tile.
template <typename S>
void composite_forward(const Lists& gl, const Lists& rl, const S* rec, const S* feat, int F, const S* ray_az,
                       const S* ray_el, const S* dirs, S rmin, S rmax, S* out_feat, S* out_rsum, S* out_alpha,
                       S* out_median, int nthreads) {
  const int64_t tiles = gl.off.size(0) - 1;
  const int64_t* roff = rl.off.data_ptr<int64_t>();
  const int64_t* goff = gl.off.data_ptr<int64_t>();
  const int32_t* gids = gl.items.data_ptr<int32_t>();
#pragma omp parallel num_threads(nthreads)
  {
    TileRays<S> tr;
    std::vector<S> T, rsum, median, acc, pw;
    std::vector<uint8_t> alive, crossed;
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < tiles; ++tile) {
      const int64_t P = roff[tile + 1] - roff[tile];
      if (P == 0) continue;
      tr.load(rl, tile, ray_az, ray_el, dirs);
      T.assign(P, S(1));
      rsum.assign(P, S(0));
      median.assign(P, rmax);
      acc.assign(P * F, S(0));
      pw.resize(P);
      alive.assign(P, 1);
      crossed.assign(P, 0);
      int64_t live = P;
      for (int64_t e = goff[tile]; e < goff[tile + 1] && live > 0; ++e) {
        const int64_t gi = gids[e];
        const S* g = rec + gi * REC;
        powers(g, tr, pw.data());
        const S* f = feat + gi * F;
        Pair<S> p;
        for (int64_t k = 0; k < P; ++k) {
          if (!alive[k] || !evaluate(g, pw[k], &tr.u[3 * k], rmin, rmax, p)) continue;
          const S nT = T[k] * (S(1) - p.a);
          if (nT <= S(T_MIN)) {  // keep only while the transmittance stays above 1e-4
            alive[k] = 0;
            --live;
            continue;
          }
          const S w = p.a * T[k];
          for (int c = 0; c < F; ++c) acc[k * F + c] += w * f[c];
          rsum[k] += w * p.r;
          if (!crossed[k] && nT <= S(0.5)) {  // T was above 0.5 (it only falls by composited pairs)
            median[k] = p.r;
            crossed[k] = 1;
          }
          T[k] = nT;
        }
      }
      for (int64_t k = 0; k < P; ++k) {
        const int64_t j = tr.id[k];
        for (int c = 0; c < F; ++c) out_feat[j * F + c] = acc[k * F + c];
        out_rsum[j] = rsum[k];
        out_alpha[j] = S(1) - T[k];
        out_median[j] = median[k];
      }
    }
  }
}

// The forward's walk again with the gradients: dL/dalpha_i = T_i c_i - (sum over later
// pairs of w_j c_j) / (1 - alpha_i), the later sum being the total (from the forward's
// outputs) less the running prefix. Per Gaussian the sums over the tile's rays go to a
// per-thread buffer; the buffers are added in thread order.
template <typename S>
void composite_backward(const Lists& gl, const Lists& rl, const S* rec, const S* feat, int F, const S* ray_az,
                        const S* ray_el, const S* dirs, S rmin, S rmax, const S* o_feat, const S* o_rsum,
                        const S* o_alpha, const S* g_feat, const S* g_rsum, const S* g_alpha, const S* g_median,
                        int64_t N, double* grads, int nthreads) {
  const int64_t tiles = gl.off.size(0) - 1;
  const int64_t* roff = rl.off.data_ptr<int64_t>();
  const int64_t* goff = gl.off.data_ptr<int64_t>();
  const int32_t* gids = gl.items.data_ptr<int32_t>();
  const int K = G_F + F;
  std::vector<double> buffers(size_t(nthreads > 1 ? nthreads - 1 : 0) * N * K, 0.0);
#pragma omp parallel num_threads(nthreads)
  {
    const int me = omp_get_thread_num();
    double* mine = me == 0 ? grads : buffers.data() + size_t(me - 1) * N * K;  // thread 0 writes the output
    TileRays<S> tr;
    std::vector<S> T, prefix, total, gf, gR, gA, gM, pw;
    std::vector<uint8_t> alive, crossed;
    std::vector<double> d(K);
#pragma omp for schedule(static, 1)
    for (int64_t tile = 0; tile < tiles; ++tile) {
      const int64_t P = roff[tile + 1] - roff[tile];
      if (P == 0) continue;
      tr.load(rl, tile, ray_az, ray_el, dirs);
      T.assign(P, S(1));
      prefix.assign(P, S(0));
      total.resize(P);
      gf.resize(P * F);
      gR.resize(P);
      gA.resize(P);
      gM.resize(P);
      pw.resize(P);
      alive.assign(P, 1);
      crossed.assign(P, 0);
      for (int64_t k = 0; k < P; ++k) {
        const int64_t j = tr.id[k];
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
      int64_t live = P;
      for (int64_t e = goff[tile]; e < goff[tile + 1] && live > 0; ++e) {
        const int64_t gi = gids[e];
        const S* g = rec + gi * REC;
        powers(g, tr, pw.data());
        const S* f = feat + gi * F;
        std::fill(d.begin(), d.end(), 0.0);
        bool touched = false;
        Pair<S> p;
        for (int64_t k = 0; k < P; ++k) {
          if (!alive[k] || !evaluate(g, pw[k], &tr.u[3 * k], rmin, rmax, p)) continue;
          const S nT = T[k] * (S(1) - p.a);
          if (nT <= S(T_MIN)) {
            alive[k] = 0;
            --live;
            continue;
          }
          touched = true;
          const S w = p.a * T[k];
          const S* gfk = &gf[k * F];
          S ci = gA[k] + gR[k] * p.r;
          for (int c = 0; c < F; ++c) {
            ci += gfk[c] * f[c];
            d[G_F + c] += double(w * gfk[c]);
          }
          prefix[k] += w * ci;
          const S suffix = total[k] - prefix[k];  // sum over the later pairs of w_j c_j
          const S dal = T[k] * ci - suffix / (S(1) - p.a);
          S dr = w * gR[k];
          if (!crossed[k] && nT <= S(0.5)) {
            dr += gM[k];
            crossed[k] = 1;
          }
          if (p.raw < S(ALPHA_MAX)) {  // alpha clamped at 0.99: no gradient to opacity or power
            const S dx = azimuth_offset(tr.az[k], g[R_AZ]);
            const S de = tr.el[k] - g[R_EL];
            const S dpow = dal * p.a;
            d[G_OP] += double(dal * p.G);
            d[G_CA] += double(S(-0.5) * dpow * dx * dx);
            d[G_CB] += double(-dpow * dx * de);
            d[G_CC] += double(S(-0.5) * dpow * de * de);
            // dx = ray azimuth - Gaussian azimuth: d power / d azimuth = ca dx + cb de
            d[G_AZ] += double(dpow * (g[R_CA] * dx + g[R_CB] * de));
            d[G_EL] += double(dpow * (g[R_CB] * dx + g[R_CC] * de));
          }
          const S* u = &tr.u[3 * k];
          const S dnum = dr / p.den, dden = -dr * p.r / p.den;  // r = num / den
          for (int c = 0; c < 3; ++c) d[G_L + c] += double(dnum * u[c]);
          d[G_Q + 0] += double(dden * u[0] * u[0]);
          d[G_Q + 1] += double(dden * S(2) * u[0] * u[1]);
          d[G_Q + 2] += double(dden * S(2) * u[0] * u[2]);
          d[G_Q + 3] += double(dden * u[1] * u[1]);
          d[G_Q + 4] += double(dden * S(2) * u[1] * u[2]);
          d[G_Q + 5] += double(dden * u[2] * u[2]);
          T[k] = nT;
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

}  // namespace

// Forward. Inputs (S = float32 or float64, N Gaussians, F features, R rays):
//   azimuth, elevation, opacities (N,), conics (N,3), quad (N,6), lin (N,3), features (N,F);
//   order (n,) int64 the drawn Gaussians by centre distance; box (N,4) int64 tile boxes;
//   ray_azimuth in [0, 360), ray_elevation (R,), directions (R,3), ray_tile (R,) int64;
//   columns, tiles of the tiling; min_range, max_range.
// Returns [features (R,F), range sum (R,), alpha (R,), median range (R,), records (N,REC),
//          Gaussian tile offsets, Gaussian ids, ray tile offsets, ray ids].
std::vector<at::Tensor> lidar_forward(at::Tensor az, at::Tensor el, at::Tensor opac, at::Tensor conics,
                                      at::Tensor quad, at::Tensor lin, at::Tensor feat, at::Tensor order,
                                      at::Tensor box, at::Tensor ray_az, at::Tensor ray_el, at::Tensor dirs,
                                      at::Tensor ray_tile, int64_t columns, int64_t tiles, double min_range,
                                      double max_range, int64_t nthreads) {
  const auto st = az.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "azimuth must be float32 or float64");
  const int64_t N = az.size(0), R = ray_az.size(0), F = feat.dim() == 2 ? feat.size(1) : 0;
  TORCH_CHECK(F >= 1, "features must be (N, F) with F >= 1");
  check(az, st, "azimuth", N, -1);
  check(el, st, "elevation", N, -1);
  check(opac, st, "opacities", N, -1);
  check(conics, st, "conics", N, 3);
  check(quad, st, "quad", N, 6);
  check(lin, st, "lin", N, 3);
  check(feat, st, "features", N, F);
  check(box, at::kLong, "box", N, 4);
  check(order, at::kLong, "order", order.size(0), -1);
  check(ray_az, st, "ray_azimuth", R, -1);
  check(ray_el, st, "ray_elevation", R, -1);
  check(dirs, st, "directions", R, 3);
  check(ray_tile, at::kLong, "ray_tile", R, -1);
  TORCH_CHECK(N < (int64_t(1) << 31), "too many Gaussians for int32 ids");
  const int nt = int(std::max<int64_t>(1, nthreads));
  Lists gl = bin_gaussians(order.data_ptr<int64_t>(), order.size(0), box.data_ptr<int64_t>(), columns, tiles);
  Lists rl = bin_rays(ray_tile.data_ptr<int64_t>(), R, tiles);
  auto opts = az.options();
  at::Tensor rec = at::empty({N, REC}, opts), o_feat = at::empty({R, F}, opts), o_rsum = at::empty({R}, opts);
  at::Tensor o_alpha = at::empty({R}, opts), o_median = at::empty({R}, opts);
  AT_DISPATCH_FLOATING_TYPES(st, "lidar_forward", [&] {
    pack_records<scalar_t>(N, az.data_ptr<scalar_t>(), el.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           opac.data_ptr<scalar_t>(), quad.data_ptr<scalar_t>(), lin.data_ptr<scalar_t>(),
                           rec.data_ptr<scalar_t>(), nt);
    composite_forward<scalar_t>(gl, rl, rec.data_ptr<scalar_t>(), feat.data_ptr<scalar_t>(), int(F),
                                ray_az.data_ptr<scalar_t>(), ray_el.data_ptr<scalar_t>(), dirs.data_ptr<scalar_t>(),
                                scalar_t(min_range), scalar_t(max_range), o_feat.data_ptr<scalar_t>(),
                                o_rsum.data_ptr<scalar_t>(), o_alpha.data_ptr<scalar_t>(),
                                o_median.data_ptr<scalar_t>(), nt);
  });
  return {o_feat, o_rsum, o_alpha, o_median, rec, gl.off, gl.items, rl.off, rl.items};
}

// Backward: dL/d(features, range sum, alpha, median range) per ray -> (N, G_F + F) float64
// per-Gaussian gradients: azimuth, elevation, conic a b c, opacity, quad (6), lin (3), features (F).
at::Tensor lidar_backward(at::Tensor rec, at::Tensor feat, at::Tensor goff, at::Tensor gids, at::Tensor roff,
                          at::Tensor rids, at::Tensor ray_az, at::Tensor ray_el, at::Tensor dirs, at::Tensor o_feat,
                          at::Tensor o_rsum, at::Tensor o_alpha, at::Tensor g_feat, at::Tensor g_rsum,
                          at::Tensor g_alpha, at::Tensor g_median, double min_range, double max_range,
                          int64_t nthreads) {
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
  const int nt = int(std::max<int64_t>(1, nthreads));
  at::Tensor grads = at::zeros({N, G_F + F}, at::kDouble);
  Lists gl{goff, gids}, rl{roff, rids};
  AT_DISPATCH_FLOATING_TYPES(st, "lidar_backward", [&] {
    composite_backward<scalar_t>(gl, rl, rec.data_ptr<scalar_t>(), feat.data_ptr<scalar_t>(), int(F),
                                 ray_az.data_ptr<scalar_t>(), ray_el.data_ptr<scalar_t>(), dirs.data_ptr<scalar_t>(),
                                 scalar_t(min_range), scalar_t(max_range), o_feat.data_ptr<scalar_t>(),
                                 o_rsum.data_ptr<scalar_t>(), o_alpha.data_ptr<scalar_t>(),
                                 g_feat.data_ptr<scalar_t>(), g_rsum.data_ptr<scalar_t>(),
                                 g_alpha.data_ptr<scalar_t>(), g_median.data_ptr<scalar_t>(), N,
                                 grads.data_ptr<double>(), nt);
  });
  return grads;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("lidar_forward", &lidar_forward, "LiDAR compositing forward over tiles of the sphere (CPU)");
  m.def("lidar_backward", &lidar_backward, "LiDAR compositing backward to the projected Gaussians (CPU)");
}
