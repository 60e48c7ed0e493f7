// Native CPU Gaussian rasterizer for omnire: projection (EWA), tile binning + depth sort,
// front-to-back compositing and a hand-written backward. Contract: omnire/rasterization.py.
//
// Two instantiations share one kernel body:
//   float : pixels processed 8 at a time in an AVX2 register (VF8) with an inline exp;
//   double: one pixel at a time (VD1), used by the float64 gradient checks.
// Projection and its backward always run in double (cheap, O(N)), which keeps huge/tiny
// scales and unnormalised quaternions well conditioned whatever the image dtype.
//
// Per-Gaussian record written by the forward and read by the pixel kernels (REC values):
//   [mean2d x, mean2d y, conic a, conic b, conic c, opacity, depth z, ext x, ext y, power floor]
// power floor = ln(1 / (255 opacity)) - 0.01: pixels with a lower exponent have alpha < 1/255.
// conic = inverse 2D covariance [[a, b], [b, c]]; ext = half-extent (pixels) of the ellipse
// outside which alpha < 1/255 for sure, so skipping those pixels changes nothing.
#include <torch/extension.h>

#include <immintrin.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

namespace {

constexpr int TILE = 16;
constexpr int TPIX = TILE * TILE;
constexpr int REC = 10;
constexpr double ALPHA_MIN = 1.0 / 255.0;
constexpr double ALPHA_MAX = 0.99;
constexpr double T_MIN = 1e-4;
constexpr double QUAT_EPS = 1e-12;

// ---------------------------------------------------------------------------------------
// Lane packs. V = values, M = lane mask.
struct VF8 {
  using S = float;
  using V = __m256;
  using M = __m256;
  static constexpr int L = 8;
  static V set1(float a) { return _mm256_set1_ps(a); }
  static V iota() { return _mm256_setr_ps(0.f, 1.f, 2.f, 3.f, 4.f, 5.f, 6.f, 7.f); }
  static V load(const float* p) { return _mm256_load_ps(p); }
  static void store(float* p, V v) { _mm256_store_ps(p, v); }
  static M load_mask(const float* p) { return _mm256_load_ps(p); }
  static void store_mask(float* p, M m) { _mm256_store_ps(p, m); }
  static M all_true() { return _mm256_castsi256_ps(_mm256_set1_epi32(-1)); }
  static M none() { return _mm256_setzero_ps(); }
  static M ge(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_GE_OQ); }
  static M lt(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_LT_OQ); }
  static M le(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_LE_OQ); }
  static M mand(M a, M b) { return _mm256_and_ps(a, b); }
  static M mandnot(M a, M b) { return _mm256_andnot_ps(b, a); }  // a & ~b
  static int count(M m) { return __builtin_popcount(_mm256_movemask_ps(m)); }
  static bool any(M m) { return _mm256_movemask_ps(m) != 0; }
  static V keep(M m, V a) { return _mm256_and_ps(m, a); }  // a where m else 0
  static V sel(M m, V a, V b) { return _mm256_blendv_ps(b, a, m); }
  static V vmin(V a, V b) { return _mm256_min_ps(a, b); }
  static V vabs(V a) { return _mm256_andnot_ps(_mm256_set1_ps(-0.f), a); }
  static V fma(V a, V b, V c) { return _mm256_fmadd_ps(a, b, c); }
  static float hsum(V v) {
    __m128 lo = _mm256_castps256_ps128(v), hi = _mm256_extractf128_ps(v, 1);
    lo = _mm_add_ps(lo, hi);
    lo = _mm_add_ps(lo, _mm_movehl_ps(lo, lo));
    lo = _mm_add_ss(lo, _mm_shuffle_ps(lo, lo, 1));
    return _mm_cvtss_f32(lo);
  }
  // exp for x <= 0 (Cephes-style range reduction + degree-5 polynomial), ~1e-7 relative.
  // Inputs below -87.3 are clamped (result ~1e-38, far below the 1/255 alpha threshold).
  static V exp(V x) {
    x = _mm256_max_ps(x, _mm256_set1_ps(-87.3f));
    x = _mm256_min_ps(x, _mm256_set1_ps(88.0f));
    V n = _mm256_round_ps(_mm256_mul_ps(x, _mm256_set1_ps(1.44269504088896341f)),
                          _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    V r = _mm256_fnmadd_ps(n, _mm256_set1_ps(0.693359375f), x);
    r = _mm256_fnmadd_ps(n, _mm256_set1_ps(-2.12194440e-4f), r);
    V p = _mm256_set1_ps(1.9875691500e-4f);
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.3981999507e-3f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(8.3334519073e-3f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(4.1665795894e-2f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.6666665459e-1f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(5.0000001201e-1f));
    V r2 = _mm256_mul_ps(r, r);
    V y = _mm256_fmadd_ps(p, r2, _mm256_add_ps(r, _mm256_set1_ps(1.f)));
    __m256i e = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
    return _mm256_mul_ps(y, _mm256_castsi256_ps(e));
  }
};

struct VD1 {
  using S = double;
  using V = double;
  using M = bool;
  static constexpr int L = 1;
  static V set1(double a) { return a; }
  static V iota() { return 0.0; }
  static V load(const double* p) { return *p; }
  static void store(double* p, V v) { *p = v; }
  static M load_mask(const double* p) { return *p != 0.0; }
  static void store_mask(double* p, M m) { *p = m ? 1.0 : 0.0; }
  static M all_true() { return true; }
  static M none() { return false; }
  static M ge(V a, V b) { return a >= b; }
  static M lt(V a, V b) { return a < b; }
  static M le(V a, V b) { return a <= b; }
  static M mand(M a, M b) { return a && b; }
  static M mandnot(M a, M b) { return a && !b; }
  static int count(M m) { return m ? 1 : 0; }
  static bool any(M m) { return m; }
  static V keep(M m, V a) { return m ? a : 0.0; }
  static V sel(M m, V a, V b) { return m ? a : b; }
  static V vmin(V a, V b) { return a < b ? a : b; }
  static V vabs(V a) { return std::fabs(a); }
  static V fma(V a, V b, V c) { return a * b + c; }
  static double hsum(V v) { return v; }
  static V exp(V x) { return std::exp(x); }
};

template <typename S> struct PackFor;
template <> struct PackFor<float> { using P = VF8; };
template <> struct PackFor<double> { using P = VD1; };

// ---------------------------------------------------------------------------------------
// Camera and per-Gaussian projection (double precision).
struct Camera {
  double R[9], t[3];
  double fx, fy, cx, cy;
  double lim_xp, lim_xn, lim_yp, lim_yn;  // clamp range of x/z, y/z for the Jacobian
  int W, H;
};

Camera make_camera(const at::Tensor& viewmat, const at::Tensor& K, int W, int H) {
  auto vm = viewmat.detach().to(at::kCPU, at::kDouble).contiguous();
  auto k = K.detach().to(at::kCPU, at::kDouble).contiguous();
  const double* v = vm.data_ptr<double>();
  const double* kk = k.data_ptr<double>();
  Camera c;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.R[i * 3 + j] = v[i * 4 + j];
    c.t[i] = v[i * 4 + 3];
  }
  c.fx = kk[0];
  c.fy = kk[4];
  c.cx = kk[2];
  c.cy = kk[5];
  c.W = W;
  c.H = H;
  // Jacobian clamp as in gsplat: the visible FoV plus 15% of it on each side (1.3x total).
  const double tan_x = 0.5 * W / c.fx, tan_y = 0.5 * H / c.fy;
  c.lim_xp = (W - c.cx) / c.fx + 0.3 * tan_x;
  c.lim_xn = c.cx / c.fx + 0.3 * tan_x;
  c.lim_yp = (H - c.cy) / c.fy + 0.3 * tan_y;
  c.lim_yn = c.cy / c.fy + 0.3 * tan_y;
  return c;
}

// Lanes: the projection and its backward are written once over a lane type D, double (one
// row) or D4 (four rows in an AVX2 register; GCC vector extensions, elementwise operators,
// comparisons give lane masks, `mask ? a : b` selects). Same operations, same numbers.
typedef double D4 __attribute__((vector_size(32)));
template <typename D> using MaskOf = decltype(D{} < D{});
inline double lane_sqrt(double x) { return std::sqrt(x); }
inline D4 lane_sqrt(D4 x) { return D4(_mm256_sqrt_pd(__m256d(x))); }
template <typename D> inline D splat(double x) { return D{} + x; }

// What the projection of a Gaussian in depth computes, and its backward reads.
template <typename D>
struct ProjCore {
  D qn[4], qnorm, s[3];
  D Rq[9], M[9], Sig3[6];  // Sig3: xx, xy, xz, yy, yz, zz
  D t[3], u, v;            // camera-space mean, clamped x/z, y/z
  MaskOf<D> unit, u_free, v_free;  // |q| > QUAT_EPS; x/z, y/z inside the clamp range
  D T[6];                  // J * Rview (2x3)
  D cov[3];                // 2D covariance a, b, c (with eps2d)
  D det, conic[3];         // conic meaningful where det > 0
};

struct Proj : ProjCore<double> {
  bool in_depth;   // near <= z <= far: mean2d defined
  bool ok;         // conic defined and finite
  double m2d[2];
};

// Index of entry (i, j) of a symmetric 3x3 matrix stored as xx, xy, xz, yy, yz, zz.
constexpr int SYM3[3][3] = {{0, 1, 2}, {1, 3, 4}, {2, 4, 5}};

// From the camera-space mean t (p.t, set by the caller) and iz = 1 / t_z: rotation, 3D and
// 2D covariance, conic. Straight-line code (no lane exits): the caller decides validity.
template <typename D>
void project_core(const D quat[4], const D scale[3], D iz, const Camera& cam, double eps2d, ProjCore<D>& p) {
  // Rotation of the normalised quaternion; |q| <= 1e-12 is the identity (zero gradient).
  p.qnorm = lane_sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  p.unit = p.qnorm > QUAT_EPS;
  const D iq = 1.0 / p.qnorm;
  for (int i = 0; i < 4; ++i) p.qn[i] = p.unit ? quat[i] * iq : splat<D>(i == 0 ? 1.0 : 0.0);
  const D w = p.qn[0], x = p.qn[1], y = p.qn[2], zq = p.qn[3];
  D* R = p.Rq;
  R[0] = 1 - 2 * (y * y + zq * zq); R[1] = 2 * (x * y - w * zq);     R[2] = 2 * (x * zq + w * y);
  R[3] = 2 * (x * y + w * zq);     R[4] = 1 - 2 * (x * x + zq * zq); R[5] = 2 * (y * zq - w * x);
  R[6] = 2 * (x * zq - w * y);     R[7] = 2 * (y * zq + w * x);     R[8] = 1 - 2 * (x * x + y * y);
  for (int j = 0; j < 3; ++j) p.s[j] = scale[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) p.M[i * 3 + j] = R[i * 3 + j] * p.s[j];
  // Sig3 = M M^T
  int k = 0;
  for (int i = 0; i < 3; ++i)
    for (int j = i; j < 3; ++j, ++k)
      p.Sig3[k] = p.M[i * 3] * p.M[j * 3] + p.M[i * 3 + 1] * p.M[j * 3 + 1] + p.M[i * 3 + 2] * p.M[j * 3 + 2];

  const D ur = p.t[0] * iz, vr = p.t[1] * iz;
  const D lxp = splat<D>(cam.lim_xp), lxn = splat<D>(-cam.lim_xn), lyp = splat<D>(cam.lim_yp), lyn = splat<D>(-cam.lim_yn);
  const D umax = lxn < ur ? ur : lxn, vmax = lyn < vr ? vr : lyn;  // std::max(-lim, r)
  p.u = umax < lxp ? umax : lxp;                                     // std::min(lim, .)
  p.v = vmax < lyp ? vmax : lyp;
  p.u_free = (ur > lxn) & (ur < lxp);
  p.v_free = (vr > lyn) & (vr < lyp);
  // J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]];  T = J * Rview
  const D J00 = cam.fx * iz, J02 = -cam.fx * p.u * iz, J11 = cam.fy * iz, J12 = -cam.fy * p.v * iz;
  for (int j = 0; j < 3; ++j) {
    p.T[j] = J00 * cam.R[j] + J02 * cam.R[6 + j];
    p.T[3 + j] = J11 * cam.R[3 + j] + J12 * cam.R[6 + j];
  }
  // cov = T Sig3 T^T (+ eps2d on the diagonal)
  D TS[6];  // T * Sig3 (2x3)
  for (int r = 0; r < 2; ++r)
    for (int j = 0; j < 3; ++j)
      TS[r * 3 + j] = p.T[r * 3] * p.Sig3[SYM3[0][j]] + p.T[r * 3 + 1] * p.Sig3[SYM3[1][j]] +
                      p.T[r * 3 + 2] * p.Sig3[SYM3[2][j]];
  p.cov[0] = TS[0] * p.T[0] + TS[1] * p.T[1] + TS[2] * p.T[2] + eps2d;
  p.cov[1] = TS[0] * p.T[3] + TS[1] * p.T[4] + TS[2] * p.T[5];
  p.cov[2] = TS[3] * p.T[3] + TS[4] * p.T[4] + TS[5] * p.T[5] + eps2d;
  p.det = p.cov[0] * p.cov[2] - p.cov[1] * p.cov[1];
  const D idet = 1.0 / p.det;
  p.conic[0] = p.cov[2] * idet;
  p.conic[1] = -p.cov[1] * idet;
  p.conic[2] = p.cov[0] * idet;
}

// From p.t (camera-space mean) and iz = 1 / t_z: in_depth (near < z < far, z > 0, strictly
// inside like the reference, and a finite 2D mean) and the 2D mean; ok false. False when
// the row is not in depth.
inline bool place_mean2d(Proj& p, double iz, const Camera& cam, double near, double far) {
  const double z = p.t[2];
  p.ok = false;
  p.in_depth = (z > near && z < far && z > 0.0);
  if (!p.in_depth) return false;
  p.m2d[0] = cam.fx * p.t[0] * iz + cam.cx;
  p.m2d[1] = cam.fy * p.t[1] * iz + cam.cy;
  p.in_depth = std::isfinite(p.m2d[0]) && std::isfinite(p.m2d[1]);
  return p.in_depth;
}

// The conic of a projection in depth is usable: positive, finite determinant and entries.
inline bool conic_ok(const Proj& p) {
  return p.det > 0.0 && std::isfinite(p.det) && std::isfinite(p.cov[0]) && std::isfinite(p.cov[2]) &&
         std::isfinite(p.conic[0]) && std::isfinite(p.conic[1]) && std::isfinite(p.conic[2]);
}

template <typename S>
void project_one(const S* mean, const S* quat, const S* scale, const Camera& cam, double near,
                 double far, double eps2d, Proj& p) {
  double m[3] = {double(mean[0]), double(mean[1]), double(mean[2])};
  for (int i = 0; i < 3; ++i)
    p.t[i] = cam.R[i * 3] * m[0] + cam.R[i * 3 + 1] * m[1] + cam.R[i * 3 + 2] * m[2] + cam.t[i];
  // one division per quantity divided by (z, |q|, det), multiplications after it: divisions
  // are the slowest arithmetic here and this runs for every row, forward and backward
  const double iz = 1.0 / p.t[2];
  if (!place_mean2d(p, iz, cam, near, far)) return;
  const double q[4] = {double(quat[0]), double(quat[1]), double(quat[2]), double(quat[3])};
  const double sc[3] = {double(scale[0]), double(scale[1]), double(scale[2])};
  project_core(q, sc, iz, cam, eps2d, p);
  p.ok = conic_ok(p);
}

// project_one of n <= 4 rows at once on the lanes of D4 (spare lanes repeat the first row):
// the same numbers per row; of each Proj only what the forward reads afterwards is set
// (t, cov, det, conic, m2d, in_depth, ok).
template <typename S>
void project_four(const S* const mean[4], const S* const quat[4], const S scale[4][3], int n, const Camera& cam,
                  double near, double far, double eps2d, Proj out[4]) {
  D4 m[3], q[4], sc[3];
  for (int l = 0; l < 4; ++l) {
    const int src = l < n ? l : 0;
    for (int j = 0; j < 3; ++j) {
      m[j][l] = double(mean[src][j]);
      sc[j][l] = double(scale[src][j]);
    }
    for (int j = 0; j < 4; ++j) q[j][l] = double(quat[src][j]);
  }
  ProjCore<D4> p;
  for (int i = 0; i < 3; ++i) p.t[i] = cam.R[i * 3] * m[0] + cam.R[i * 3 + 1] * m[1] + cam.R[i * 3 + 2] * m[2] + cam.t[i];
  const D4 iz = 1.0 / p.t[2];
  project_core(q, sc, iz, cam, eps2d, p);
  for (int l = 0; l < n; ++l) {
    Proj& o = out[l];
    for (int i = 0; i < 3; ++i) o.t[i] = p.t[i][l];
    if (!place_mean2d(o, iz[l], cam, near, far)) continue;
    for (int i = 0; i < 3; ++i) {
      o.cov[i] = p.cov[i][l];
      o.conic[i] = p.conic[i][l];
    }
    o.det = p.det[l];
    o.ok = conic_ok(o);
  }
}

// ---------------------------------------------------------------------------------------
// Forward projection + binning.
// Narrow a tile rect [x0, x1) x [y0, y1) (from the 3-sigma radius, which decides whether a
// Gaussian counts as drawn) to the tiles its alpha >= 1/255 extent (ex, ey around the mean,
// pixel centres) can reach: the others would find no pixel in its span. About a third of
// the pairs of a trained scene. May leave the rect empty; binning then skips it.
inline void narrow_rect(int32_t* rc, double mx, double my, double ex, double ey, int tilesX, int tilesY) {
  const double tx0 = std::floor((mx - ex - 0.5) / TILE), tx1 = std::floor((mx + ex - 0.5) / TILE) + 1;
  const double ty0 = std::floor((my - ey - 0.5) / TILE), ty1 = std::floor((my + ey - 0.5) / TILE) + 1;
  rc[0] = std::max(rc[0], int32_t(std::min<double>(tilesX, std::max(0.0, tx0))));
  rc[2] = std::min(rc[2], int32_t(std::min<double>(tilesX, std::max(0.0, tx1))));
  rc[1] = std::max(rc[1], int32_t(std::min<double>(tilesY, std::max(0.0, ty0))));
  rc[3] = std::min(rc[3], int32_t(std::min<double>(tilesY, std::max(0.0, ty1))));
  if (rc[2] < rc[0]) rc[2] = rc[0];
  if (rc[3] < rc[1]) rc[3] = rc[1];
}

// The region where a Gaussian can reach alpha >= 1/255, from its record as stored (the
// values the pixel loops evaluate): the ellipse {q <= T}, q = a u^2 + 2 b u v + c v^2 around
// the mean (conic [a b; b c]). q <= tq is alpha >= 1/255 (tq = -2 (floor + 0.01), the
// record's power floor); T exceeds it by 0.01 (half the floor's margin, in power) and by a
// relative 1e-5 (a + c)^2 / det, which bounds the float rounding of the pixel loops' power:
// that rounding is at most a few ulp of a u^2 + c v^2, and (a + c)^2 / det bounds
// (a u^2 + c v^2) / q on the ellipse (it is at least the conic's condition number). So a
// pixel outside it fails the alpha test in the loops: skipping it changes nothing. False for
// a degenerate stored conic.
struct AlphaReach {
  double mx, my, a, b, c, det, T;
};

template <typename S>
inline bool alpha_reach(const S* g, AlphaReach* r) {
  const double a = g[2], b = g[3], c = g[4];
  const double det = a * c - b * b;
  if (!(a > 0 && c > 0 && det > 0 && std::isfinite(det))) return false;
  const double tq = -2.0 * (double(g[9]) + 0.01);
  const double T = std::max(0.0, (tq + 0.01) * (1.0 + 1e-5 * (a + c) * (a + c) / det));
  if (!std::isfinite(T)) return false;
  *r = {double(g[0]), double(g[1]), a, b, c, det, T};
  return true;
}

// Half-extents (ex, ey; pixels) of alpha_reach's ellipse: its bounding box around the mean,
// sqrt(T c / det) and sqrt(T a / det). False (ex, ey untouched) for a degenerate stored conic.
template <typename S>
inline bool alpha_extent(const S* g, double* ex, double* ey) {
  AlphaReach r;
  if (!alpha_reach(g, &r)) return false;
  *ex = std::sqrt(r.T * r.c / r.det);
  *ey = std::sqrt(r.T * r.a / r.det);
  return true;
}

// Whether alpha_reach's ellipse holds a pixel centre of the tile (tx, ty) of a W x H image:
// the least q over the rectangle of its pixel centres is at most T. q is convex, so that
// least value is 0 when the rectangle holds the mean, else on one of its edges, where q is
// a parabola whose vertex, clamped to the edge, is the edge's least. A tile it fails has
// no pixel the Gaussian can paint (alpha_reach), so leaving it out of that tile's list
// changes nothing; about a third of the pairs a trained scene's ellipse bounding boxes give
// (thin, tilted Gaussians) are such.
// ``bc`` = b / c and ``ba`` = b / a (the edges' vertices).
inline bool reaches_tile(const AlphaReach& r, double bc, double ba, int tx, int ty, int W, int H) {
  const double x0 = tx * TILE + 0.5 - r.mx, x1 = std::min(tx * TILE + TILE, W) - 0.5 - r.mx;
  const double y0 = ty * TILE + 0.5 - r.my, y1 = std::min(ty * TILE + TILE, H) - 0.5 - r.my;
  if (x0 <= 0.0 && 0.0 <= x1 && y0 <= 0.0 && 0.0 <= y1) return true;
  auto q = [&](double u, double v) { return r.a * u * u + 2.0 * r.b * u * v + r.c * v * v; };
  // the least of the four edges' least values is at most T when one of them is (all finite)
  return q(x0, std::clamp(-bc * x0, y0, y1)) <= r.T || q(x1, std::clamp(-bc * x1, y0, y1)) <= r.T ||
         q(std::clamp(-ba * y0, x0, x1), y0) <= r.T || q(std::clamp(-ba * y1, x0, x1), y1) <= r.T;
}

// The tiles of a Gaussian's rect ``rc`` (x0, y0, x1, y1) its alpha ellipse reaches
// (reaches_tile), as bits in row-major order over the rect; every bit for a single tile or a
// degenerate stored conic. Rects of more than 64 tiles are not tested (all tiles kept).
constexpr int MAX_TESTED_TILES = 64;
template <typename S>
inline uint64_t reached_tiles(const S* g, const int32_t* rc, int W, int H) {
  const int w = rc[2] - rc[0], n = w * (rc[3] - rc[1]);
  AlphaReach r;
  if (n <= 1 || n > MAX_TESTED_TILES || !alpha_reach(g, &r)) return ~uint64_t(0);
  const double bc = r.b / r.c, ba = r.b / r.a;
  uint64_t bits = 0;
  for (int k = 0; k < n; ++k)
    if (reaches_tile(r, bc, ba, rc[0] + k % w, rc[1] + k / w, W, H)) bits |= uint64_t(1) << k;
  return bits;
}

// Tile rect [x0, y0, x1, y1) of a projected Gaussian's 3-sigma radius (the "drawn" test:
// false when it reaches no tile); radius = ceil(3 sqrt(lambda_max)), at most 1e9.
inline bool radius_rect(const Proj& p, int tilesX, int tilesY, double* radius, int32_t* rc) {
  const double mid = 0.5 * (p.cov[0] + p.cov[2]);
  const double lam = mid + std::sqrt(std::max(0.1, mid * mid - p.det));
  double r = std::ceil(3.0 * std::sqrt(lam));
  if (!std::isfinite(r)) return false;
  r = std::min(r, 1e9);
  const double mx = p.m2d[0], my = p.m2d[1];
  rc[0] = int(std::min<double>(tilesX, std::max(0.0, std::floor((mx - r) / TILE))));
  rc[1] = int(std::min<double>(tilesY, std::max(0.0, std::floor((my - r) / TILE))));
  rc[2] = int(std::min<double>(tilesX, std::max(0.0, std::ceil((mx + r) / TILE))));
  rc[3] = int(std::min<double>(tilesY, std::max(0.0, std::ceil((my + r) / TILE))));
  *radius = r;
  return rc[0] < rc[2] && rc[1] < rc[3];
}

// The record (layout at the top) of a drawn Gaussian with opacity o, and its tile rect
// narrowed to its alpha >= 1/255 extent (alpha_extent of the stored values).
template <typename S>
inline void write_record(const Proj& p, double o, int tilesX, int tilesY, S* g, int32_t* rc) {
  const double tq = 2.0 * std::log(o / ALPHA_MIN);
  g[0] = S(p.m2d[0]); g[1] = S(p.m2d[1]);
  g[2] = S(p.conic[0]); g[3] = S(p.conic[1]); g[4] = S(p.conic[2]);
  g[5] = S(o); g[6] = S(p.t[2]);
  g[9] = S(-0.5 * tq - 0.01);
  double ex, ey;
  if (!alpha_extent(g, &ex, &ey)) {  // degenerate stored conic: from the double covariance, with margins
    ex = std::sqrt(std::max(0.0, tq) * p.cov[0]) * 1.02 + 0.5;
    ey = std::sqrt(std::max(0.0, tq) * p.cov[2]) * 1.02 + 0.5;
  }
  g[7] = S(std::min(ex, 1e9)); g[8] = S(std::min(ey, 1e9));
  narrow_rect(rc, p.m2d[0], p.m2d[1], ex, ey, tilesX, tilesY);
}

template <typename S>
void project_all(int64_t N, const S* means, const S* quats, const S* scales, const S* opac,
                 const Camera& cam, double near, double far, double eps2d, int tilesX, int tilesY,
                 S* rec, S* means2d, int32_t* radii, int32_t* rect, int nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t i = 0; i < N; ++i) {
    Proj p;
    project_one(means + 3 * i, quats + 4 * i, scales + 3 * i, cam, near, far, eps2d, p);
    radii[i] = 0;
    for (int k = 0; k < 4; ++k) rect[4 * i + k] = 0;
    means2d[2 * i] = p.in_depth ? S(p.m2d[0]) : S(0);
    means2d[2 * i + 1] = p.in_depth ? S(p.m2d[1]) : S(0);
    for (int k = 0; k < REC; ++k) rec[REC * i + k] = S(0);
    if (!p.ok) continue;
    double r;
    if (!radius_rect(p, tilesX, tilesY, &r, rect + 4 * i)) {
      for (int k = 0; k < 4; ++k) rect[4 * i + k] = 0;
      continue;
    }
    radii[i] = int32_t(r);
    write_record(p, double(opac[i]), tilesX, tilesY, rec + REC * i, rect + 4 * i);
  }
}

// Stable LSD radix sort of (float key >= 0, index) by key: positive IEEE floats order like
// their bit patterns. Ties keep their order in ``items``, so the result is deterministic.
// Each pass splits the items into nthreads consecutive parts: every part counts its digits,
// and part p's items of digit d go after those of digit d of parts before p (stable, and
// the same result for any number of parts). A pass whose digit is the same for every item
// moves nothing and is skipped.
void sort_by_depth(std::vector<uint64_t>& items, int nthreads) {
  const int64_t M = int64_t(items.size());
  const int P = int(std::max<int64_t>(1, std::min<int64_t>(nthreads, M / 4096)));
  std::vector<uint64_t> tmp(items.size());
  std::vector<int64_t> cnt(size_t(P) * 256);
  for (int pass = 0; pass < 4; ++pass) {
    const int shift = 32 + 8 * pass;
    std::fill(cnt.begin(), cnt.end(), 0);
#pragma omp parallel for schedule(static, 1) num_threads(P)
    for (int p = 0; p < P; ++p) {
      int64_t* c = cnt.data() + 256 * p;
      for (int64_t q = M * p / P; q < M * (p + 1) / P; ++q) ++c[(items[q] >> shift) & 0xFF];
    }
    int64_t at = 0;
    bool one_digit = false;
    for (int d = 0; d < 256; ++d) {
      int64_t in_digit = 0;
      for (int p = 0; p < P; ++p) {
        const int64_t n = cnt[256 * p + d];
        cnt[256 * p + d] = at;
        at += n;
        in_digit += n;
      }
      one_digit = one_digit || in_digit == M;
    }
    if (one_digit) continue;
#pragma omp parallel for schedule(static, 1) num_threads(P)
    for (int p = 0; p < P; ++p) {
      int64_t* c = cnt.data() + 256 * p;
      for (int64_t q = M * p / P; q < M * (p + 1) / P; ++q) tmp[c[(items[q] >> shift) & 0xFF]++] = items[q];
    }
    items.swap(tmp);
  }
}

// (depth bits, index) of the drawn Gaussians (radii > 0), nearest first.
std::vector<uint64_t> depth_order(int64_t N, const float* depth_f, const int32_t* radii, int nthreads) {
  std::vector<uint64_t> order;
  order.reserve(N);
  for (int64_t i = 0; i < N; ++i) {
    if (radii[i] <= 0) continue;
    uint32_t bits;
    float d = depth_f[i];
    std::memcpy(&bits, &d, 4);
    order.push_back((uint64_t(bits) << 32) | uint64_t(uint32_t(i)));
  }
  sort_by_depth(order, nthreads);
  return order;
}

// Tile lists of the Gaussians in ``order`` (low 32 bits: index, below ``n_records``, of their
// record in ``rec`` and rect in ``rect``), kept in that order: each in the tiles of its rect
// that its alpha ellipse reaches (reached_tiles). offsets: (ntiles+1,) int64; ids: (M,) int32.
template <typename S>
std::pair<at::Tensor, at::Tensor> bin_ordered(const std::vector<uint64_t>& order, const S* rec, const int32_t* rect,
                                              int64_t n_records, int W, int H, int nthreads) {
  const int tilesX = (W + TILE - 1) / TILE, tilesY = (H + TILE - 1) / TILE;
  const int64_t ntiles = int64_t(tilesX) * tilesY;
  auto offsets = at::zeros({ntiles + 1}, at::kLong);
  int64_t* off = offsets.data_ptr<int64_t>();
  // Bands of tile rows, each filled by one thread from the sorted list: no atomics, and the
  // lists come out already depth-sorted. First each thread sorts its share of the list into
  // per-band lists (keeping the order), so a band then reads only the Gaussians that touch it.
  const int nbands = std::max(1, std::min(tilesY, nthreads * 4));
  auto band_of = [&](int b) { return std::make_pair(int(int64_t(b) * tilesY / nbands), int(int64_t(b + 1) * tilesY / nbands)); };
  std::vector<int> band_of_row(tilesY);
  for (int b = 0; b < nbands; ++b)
    for (int ty = band_of(b).first; ty < band_of(b).second; ++ty) band_of_row[ty] = b;
  const int nparts = std::max(1, nthreads);
  const int64_t M = int64_t(order.size());
  std::vector<std::vector<int32_t>> part_band(size_t(nparts) * nbands);  // [part][band] -> indices in order
  std::vector<uint64_t> reached(n_records);  // reached_tiles of every Gaussian in the list
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int t = 0; t < nparts; ++t) {
    for (int64_t q = M * t / nparts; q < M * (t + 1) / nparts; ++q) {
      const int32_t i = int32_t(order[q] & 0xFFFFFFFFu);
      const int32_t* rc = rect + 4 * int64_t(i);
      if (rc[1] >= rc[3] || rc[0] >= rc[2]) continue;
      reached[i] = reached_tiles(rec + REC * int64_t(i), rc, W, H);
      for (int b = band_of_row[rc[1]]; b <= band_of_row[rc[3] - 1]; ++b) part_band[size_t(t) * nbands + b].push_back(i);
    }
  }
  // every index of band b, in list order
  auto for_band = [&](int b, auto&& fn) {
    for (int t = 0; t < nparts; ++t)
      for (int32_t i : part_band[size_t(t) * nbands + b]) fn(i);
  };
  // every tile of band rows [r0, r1) that Gaussian i's list entry goes to, in order
  auto for_tiles = [&](int32_t i, int r0, int r1, auto&& fn) {
    const int32_t* rc = rect + 4 * int64_t(i);
    const int ya = std::max(rc[1], r0), yb = std::min(rc[3], r1), w = rc[2] - rc[0];
    const uint64_t bits = reached[i];
    for (int ty = ya; ty < yb; ++ty)
      for (int tx = rc[0]; tx < rc[2]; ++tx) {
        const int k = (ty - rc[1]) * w + (tx - rc[0]);
        if (k >= MAX_TESTED_TILES || (bits >> k) & 1) fn(int64_t(ty) * tilesX + tx);
      }
  };
  std::vector<int64_t> counts(ntiles, 0);
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
  for (int b = 0; b < nbands; ++b) {
    auto [r0, r1] = band_of(b);
    for_band(b, [&](int32_t i) { for_tiles(i, r0, r1, [&](int64_t t) { ++counts[t]; }); });
  }
  off[0] = 0;
  for (int64_t t = 0; t < ntiles; ++t) off[t + 1] = off[t] + counts[t];
  auto ids = at::empty({off[ntiles]}, at::kInt);
  int32_t* idp = ids.data_ptr<int32_t>();
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
  for (int b = 0; b < nbands; ++b) {
    auto [r0, r1] = band_of(b);
    const int64_t first = int64_t(r0) * tilesX;
    std::vector<int64_t> cur(off + first, off + int64_t(r1) * tilesX);
    for_band(b, [&](int32_t i) { for_tiles(i, r0, r1, [&](int64_t t) { idp[cur[t - first]++] = i; }); });
  }
  return {offsets, ids};
}

// ---------------------------------------------------------------------------------------
// Pixel kernels. Per tile, pixel state lives in 256-entry arrays (row-major 16x16);
// Gaussians are the outer loop so per-Gaussian gradient sums stay in registers.

// One pixel's entry of the alive mask: all-ones bits for VF8 lanes, 1/0 for VD1.
template <int L, typename S>
inline void set_alive(S* p, bool in) {
  if constexpr (L > 1) {
    const uint32_t bits = in ? 0xFFFFFFFFu : 0u;
    std::memcpy(p, &bits, sizeof(uint32_t));
  } else {
    *p = in ? S(1) : S(0);
  }
}

// Rows / lane groups of the tile that the Gaussian's ellipse extent can touch.
struct Span { int r0, r1, v0, v1; };

template <int L, typename S>
inline Span span_of(const S* g, int x0, int y0, int tw, int th) {
  const double mx = g[0], my = g[1], ex = g[7], ey = g[8];
  // pixel centre j + 0.5 within [m - e, m + e]
  const double ra = std::ceil(my - ey - y0 - 0.5), rb = std::floor(my + ey - y0 - 0.5);
  const double ca = std::ceil(mx - ex - x0 - 0.5), cb = std::floor(mx + ex - x0 - 0.5);
  Span s;
  s.r0 = int(std::max(0.0, ra));
  s.r1 = int(std::min(double(th - 1), rb)) + 1;
  const int c0 = int(std::max(0.0, ca));
  const int c1 = int(std::min(double(tw - 1), cb));
  s.v0 = c0 / L;
  s.v1 = c1 / L + 1;
  if (c1 < c0) s.v1 = s.v0;
  return s;
}

// A tile's list jumps through the records (depth order over the whole image): fetch the
// record (and colour) of the Gaussian PREFETCH_AHEAD entries on while this one is drawn.
constexpr int PREFETCH_AHEAD = 4;
template <typename S>
inline void prefetch_record(const S* rec, const S* colors, int D, int64_t gi) {
  __builtin_prefetch(rec + REC * gi);
  __builtin_prefetch(rec + REC * gi + REC - 1);
  __builtin_prefetch(colors + int64_t(D) * gi);
}

template <typename S>
void render_forward(const Camera& cam, int D, int tilesX, int tilesY, const S* rec, const S* colors,
                    const int64_t* off, const int32_t* ids, S* out_acc, S* out_dn, S* out_a,
                    int nthreads) {
  using P = typename PackFor<S>::P;
  using V = typename P::V;
  using M = typename P::M;
  constexpr int L = P::L;
  const int W = cam.W, H = cam.H;
  const int64_t ntiles = int64_t(tilesX) * tilesY;
#pragma omp parallel num_threads(nthreads)
  {
    alignas(32) S T[TPIX], alive[TPIX], accD[TPIX], accA[TPIX];
    std::vector<S> accC_store(size_t(D) * TPIX + 8);
    S* accC = accC_store.data();
    // accC needs 32-byte alignment for aligned loads
    {
      uintptr_t a = reinterpret_cast<uintptr_t>(accC);
      accC += ((32 - (a & 31)) & 31) / sizeof(S);
    }
    const V ones = P::set1(S(1)), amin = P::set1(S(ALPHA_MIN)), amax = P::set1(S(ALPHA_MAX));
    const V tmin = P::set1(S(T_MIN)), mhalf = P::set1(S(-0.5)), lane = P::iota(), zero = P::set1(S(0));
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < ntiles; ++tile) {
      const int tx = int(tile % tilesX), ty = int(tile / tilesX);
      const int x0 = tx * TILE, y0 = ty * TILE;
      const int tw = std::min(TILE, W - x0), th = std::min(TILE, H - y0);
      int n_alive = 0;
      for (int j = 0; j < TILE; ++j)
        for (int i = 0; i < TILE; ++i) {
          const bool in = (i < tw && j < th);
          set_alive<L>(&alive[j * TILE + i], in);
          n_alive += in;
        }
      for (int k = 0; k < TPIX; ++k) { T[k] = S(1); accD[k] = S(0); accA[k] = S(0); }
      for (int k = 0; k < D * TPIX; ++k) accC[k] = S(0);

      for (int64_t e = off[tile]; e < off[tile + 1] && n_alive > 0; ++e) {
        const int64_t gi = ids[e];
        if (e + PREFETCH_AHEAD < off[tile + 1]) prefetch_record(rec, colors, D, ids[e + PREFETCH_AHEAD]);
        const S* g = rec + REC * gi;
        const S* col = colors + int64_t(D) * gi;
        const Span sp = span_of<L>(g, x0, y0, tw, th);
        const V mx = P::set1(g[0]), my = P::set1(g[1]);
        const V ca = P::set1(g[2]), cb = P::set1(g[3]), cc = P::set1(g[4]);
        const V op = P::set1(g[5]), zz = P::set1(g[6]);
        // A lane group whose every pixel has power below g[9] (0.01 below ln(1 / (255 o)), the
        // least power with alpha >= 1/255; 1% in alpha, far above the rounding of exp) fails
        // the alpha test for sure: skipped before the exp. Changes no pixel.
        const V pthr = P::set1(g[9]);
        // dx and the power's dx-only term of each lane group, the same for every row
        V dxs[TILE / L], xterm[TILE / L];
        for (int vg = sp.v0; vg < sp.v1; ++vg) {
          dxs[vg] = P::set1(S(x0 + vg * L) + S(0.5)) + lane - mx;
          xterm[vg] = mhalf * ca * dxs[vg] * dxs[vg];
        }
        for (int r = sp.r0; r < sp.r1; ++r) {
          const V dy = P::set1(S(y0 + r) + S(0.5)) - my;
          const V cdy = cb * dy, hdy2 = mhalf * cc * dy * dy;
          for (int vg = sp.v0; vg < sp.v1; ++vg) {
            const int idx = r * TILE + vg * L;
            M m = P::load_mask(&alive[idx]);
            if (!P::any(m)) continue;
            const V dx = dxs[vg];
            const V power = xterm[vg] - cdy * dx + hdy2;
            if (!P::any(P::mand(m, P::ge(power, pthr)))) continue;
            const V al = P::vmin(amax, op * P::exp(power));
            m = P::mand(m, P::mand(P::ge(al, amin), P::le(power, zero)));
            if (!P::any(m)) continue;
            const V Tv = P::load(&T[idx]);
            const V nT = Tv * (ones - al);
            const M stop = P::mand(m, P::le(nT, tmin));  // keep only while T stays > 1e-4
            if (P::any(stop)) {
              n_alive -= P::count(stop);
              P::store_mask(&alive[idx], P::mandnot(P::load_mask(&alive[idx]), stop));
              m = P::mandnot(m, stop);
            }
            const V w = P::keep(m, al * Tv);
            for (int c = 0; c < D; ++c)
              P::store(&accC[c * TPIX + idx], P::fma(w, P::set1(col[c]), P::load(&accC[c * TPIX + idx])));
            P::store(&accD[idx], P::fma(w, zz, P::load(&accD[idx])));
            P::store(&accA[idx], P::load(&accA[idx]) + w);
            P::store(&T[idx], P::sel(m, nT, Tv));
          }
        }
      }
      for (int j = 0; j < th; ++j)
        for (int i = 0; i < tw; ++i) {
          const int k = j * TILE + i;
          const int64_t pix = int64_t(y0 + j) * W + (x0 + i);
          for (int c = 0; c < D; ++c) out_acc[pix * D + c] = accC[c * TPIX + k];
          out_dn[pix] = accD[k];
          out_a[pix] = accA[k];
        }
    }
  }
}

// Gradient slots per Gaussian in the per-thread buffers.
enum { G_MX = 0, G_MY, G_CA, G_CB, G_CC, G_OP, G_Z, G_AX, G_AY, G_COL };

template <typename S>
void render_backward(const Camera& cam, int D, int tilesX, int tilesY, const S* rec, const S* colors,
                     const int64_t* off, const int32_t* ids, const S* acc, const S* dn, const S* aa,
                     const S* g_acc, const S* g_dn, const S* g_a, int64_t N, double* gbuf, uint8_t* touched,
                     int nthreads) {
  using P = typename PackFor<S>::P;
  using V = typename P::V;
  using M = typename P::M;
  constexpr int L = P::L;
  const int W = cam.W, H = cam.H;
  const int64_t ntiles = int64_t(tilesX) * tilesY;
  const int K = G_COL + D;
#pragma omp parallel num_threads(nthreads)
  {
    double* mybuf = gbuf + int64_t(omp_get_thread_num()) * N * K;
    uint8_t* mytouched = touched + int64_t(omp_get_thread_num()) * N;
    alignas(32) S T[TPIX], alive[TPIX], pre[TPIX], stot[TPIX], gdn[TPIX], ga[TPIX];
    std::vector<S> gc_store(size_t(D) * TPIX + 8);
    S* gC = gc_store.data();
    {
      uintptr_t a = reinterpret_cast<uintptr_t>(gC);
      gC += ((32 - (a & 31)) & 31) / sizeof(S);
    }
    std::vector<V> vcol(D > 0 ? D : 1);
    const V ones = P::set1(S(1)), amin = P::set1(S(ALPHA_MIN)), amax = P::set1(S(ALPHA_MAX));
    const V tmin = P::set1(S(T_MIN)), mhalf = P::set1(S(-0.5)), lane = P::iota(), zero = P::set1(S(0));
#pragma omp for schedule(static, 1)
    for (int64_t tile = 0; tile < ntiles; ++tile) {
      const int tx = int(tile % tilesX), ty = int(tile / tilesX);
      const int x0 = tx * TILE, y0 = ty * TILE;
      const int tw = std::min(TILE, W - x0), th = std::min(TILE, H - y0);
      int n_alive = 0;
      for (int j = 0; j < TILE; ++j)
        for (int i = 0; i < TILE; ++i) {
          const int k = j * TILE + i;
          const bool in = (i < tw && j < th);
          set_alive<L>(&alive[k], in);
          n_alive += in;
          T[k] = S(1);
          pre[k] = S(0);
          if (in) {
            const int64_t pix = int64_t(y0 + j) * W + (x0 + i);
            // dL/dw_i = c_i . g_acc + z_i g_dn + g_a; stot = sum_i w_i dL/dw_i (from the forward)
            double st = double(dn[pix]) * g_dn[pix] + double(aa[pix]) * g_a[pix];
            for (int c = 0; c < D; ++c) {
              gC[c * TPIX + k] = g_acc[pix * D + c];
              st += double(acc[pix * D + c]) * g_acc[pix * D + c];
            }
            gdn[k] = g_dn[pix];
            ga[k] = g_a[pix];
            stot[k] = S(st);
          } else {
            for (int c = 0; c < D; ++c) gC[c * TPIX + k] = S(0);
            gdn[k] = ga[k] = stot[k] = S(0);
          }
        }

      for (int64_t e = off[tile]; e < off[tile + 1] && n_alive > 0; ++e) {
        const int64_t gi = ids[e];
        if (e + PREFETCH_AHEAD < off[tile + 1]) {
          const int64_t ga = ids[e + PREFETCH_AHEAD];
          prefetch_record(rec, colors, D, ga);
          __builtin_prefetch(mybuf + ga * K, 1);
          __builtin_prefetch(mybuf + ga * K + K - 1, 1);
        }
        const S* g = rec + REC * gi;
        const S* col = colors + int64_t(D) * gi;
        const Span sp = span_of<L>(g, x0, y0, tw, th);
        if (sp.r0 >= sp.r1 || sp.v0 >= sp.v1) continue;
        const V mx = P::set1(g[0]), my = P::set1(g[1]);
        const V ca = P::set1(g[2]), cb = P::set1(g[3]), cc = P::set1(g[4]);
        const V op = P::set1(g[5]), zz = P::set1(g[6]);
        const V pthr = P::set1(g[9]);  // as render_forward: lanes below it fail the alpha test
        V s_mx = zero, s_my = zero, s_ca = zero, s_cb = zero, s_cc = zero, s_op = zero, s_z = zero;
        V s_ax = zero, s_ay = zero;
        for (int c = 0; c < D; ++c) vcol[c] = zero;
        for (int r = sp.r0; r < sp.r1; ++r) {
          const V dy = P::set1(S(y0 + r) + S(0.5)) - my;
          const V cdy = cb * dy, hdy2 = mhalf * cc * dy * dy;
          for (int vg = sp.v0; vg < sp.v1; ++vg) {
            const int idx = r * TILE + vg * L;
            M m = P::load_mask(&alive[idx]);
            if (!P::any(m)) continue;
            // Must match render_forward operation for operation (same skip/stop decisions).
            const V dx = P::set1(S(x0 + vg * L) + S(0.5)) + lane - mx;
            const V power = mhalf * ca * dx * dx - cdy * dx + hdy2;
            // the forward's skip: every live lane below the power floor fails the alpha test
            // for sure, so the exp is not needed (the decisions stay the forward's)
            if (!P::any(P::mand(m, P::ge(power, pthr)))) continue;
            const V G = P::exp(power);
            const V raw = op * G;
            const V al = P::vmin(amax, raw);
            m = P::mand(m, P::mand(P::ge(al, amin), P::le(power, zero)));
            if (!P::any(m)) continue;
            const V Tv = P::load(&T[idx]);
            const V nT = Tv * (ones - al);
            const M stop = P::mand(m, P::le(nT, tmin));  // keep only while T stays > 1e-4
            if (P::any(stop)) {
              n_alive -= P::count(stop);
              P::store_mask(&alive[idx], P::mandnot(P::load_mask(&alive[idx]), stop));
              m = P::mandnot(m, stop);
              if (!P::any(m)) continue;
            }
            const V w = P::keep(m, al * Tv);
            V vi = P::load(&ga[idx]);
            vi = P::fma(zz, P::load(&gdn[idx]), vi);
            for (int c = 0; c < D; ++c) {
              const V gcc_ = P::load(&gC[c * TPIX + idx]);
              vi = P::fma(P::set1(col[c]), gcc_, vi);
              vcol[c] = P::fma(w, gcc_, vcol[c]);
            }
            s_z = P::fma(w, P::load(&gdn[idx]), s_z);
            const V npre = P::fma(w, vi, P::load(&pre[idx]));
            P::store(&pre[idx], npre);
            const V suffix = P::load(&stot[idx]) - npre;  // sum over later Gaussians of w_j v_j
            const V dal = P::keep(m, Tv * vi - suffix / (ones - al));
            // alpha clamped at 0.99 -> no gradient to opacity / power
            const M unc = P::lt(raw, amax);
            const V dpow = P::keep(unc, dal * al);
            s_op = s_op + P::keep(unc, dal * G);
            s_ca = P::fma(dpow, mhalf * dx * dx, s_ca);
            s_cb = s_cb - dpow * dx * dy;
            s_cc = P::fma(dpow, mhalf * dy * dy, s_cc);
            const V gmx = dpow * (ca * dx + cb * dy);
            const V gmy = dpow * (cb * dx + cc * dy);
            s_mx = s_mx + gmx;
            s_my = s_my + gmy;
            s_ax = s_ax + P::vabs(gmx);
            s_ay = s_ay + P::vabs(gmy);
            P::store(&T[idx], P::sel(m, nT, Tv));
          }
        }
        // The buffers start uninitialised: a thread's first sum for a Gaussian is stored, later
        // ones added (the same numbers as adding to zeros, without zeroing nthreads x N x K doubles)
        double* gb = mybuf + gi * K;
        const bool first = !mytouched[gi];
        mytouched[gi] = 1;
        auto put = [&](int slot, double x) { gb[slot] = first ? x : gb[slot] + x; };
        put(G_MX, P::hsum(s_mx)); put(G_MY, P::hsum(s_my));
        put(G_CA, P::hsum(s_ca)); put(G_CB, P::hsum(s_cb)); put(G_CC, P::hsum(s_cc));
        put(G_OP, P::hsum(s_op)); put(G_Z, P::hsum(s_z));
        put(G_AX, P::hsum(s_ax)); put(G_AY, P::hsum(s_ay));
        for (int c = 0; c < D; ++c) put(G_COL + c, P::hsum(vcol[c]));
      }
    }
  }
}

// Backward through the projection of Gaussians in depth, over lanes D (see ProjCore).
// Inputs: dL/dconic (a, b, c as stored, b being the off-diagonal), dL/dmean2d, dL/dz;
// ``with_cov``: the conic was defined (else only the 2D mean and depth pass gradients).
// Outputs dL/dmean, dL/dquat, dL/dscale.
template <typename D>
void project_backward_core(const ProjCore<D>& p, const Camera& cam, const D gconic[3], const D gm2d[2], D gz_depth,
                           bool with_cov, D gmean[3], D gquat[4], D gscale[3]) {
  for (int i = 0; i < 3; ++i) gscale[i] = splat<D>(0.0);
  for (int i = 0; i < 4; ++i) gquat[i] = splat<D>(0.0);
  const D iz = 1.0 / p.t[2], iz2 = iz * iz;  // multiplications after one division
  D gt[3] = {splat<D>(0.0), splat<D>(0.0), gz_depth};
  // mean2d = (fx tx/z + cx, fy ty/z + cy)
  gt[0] += gm2d[0] * cam.fx * iz;
  gt[1] += gm2d[1] * cam.fy * iz;
  gt[2] += -(gm2d[0] * cam.fx * p.t[0] + gm2d[1] * cam.fy * p.t[1]) * iz2;
  if (with_cov) {
    // conic = cov^-1: dL/dcov = -C Gc C with Gc symmetric (off-diagonal gets half of dL/db).
    const D C[4] = {p.conic[0], p.conic[1], p.conic[1], p.conic[2]};
    const D Gc[4] = {gconic[0], 0.5 * gconic[1], 0.5 * gconic[1], gconic[2]};
    D tmp[4], Gs[4];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j) tmp[i * 2 + j] = C[i * 2] * Gc[j] + C[i * 2 + 1] * Gc[2 + j];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j) Gs[i * 2 + j] = -(tmp[i * 2] * C[j] + tmp[i * 2 + 1] * C[2 + j]);
    // cov = T Sig3 T^T: dT = 2 Gs T Sig3, dSig3 = T^T Gs T
    D TS[6];
    for (int r = 0; r < 2; ++r)
      for (int j = 0; j < 3; ++j)
        TS[r * 3 + j] = p.T[r * 3] * p.Sig3[SYM3[0][j]] + p.T[r * 3 + 1] * p.Sig3[SYM3[1][j]] +
                        p.T[r * 3 + 2] * p.Sig3[SYM3[2][j]];
    D GT[6];
    for (int r = 0; r < 2; ++r)
      for (int j = 0; j < 3; ++j) GT[r * 3 + j] = 2.0 * (Gs[r * 2] * TS[j] + Gs[r * 2 + 1] * TS[3 + j]);
    D GS[9];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        D acc = splat<D>(0.0);
        for (int a = 0; a < 2; ++a)
          for (int b = 0; b < 2; ++b) acc += p.T[a * 3 + i] * Gs[a * 2 + b] * p.T[b * 3 + j];
        GS[i * 3 + j] = acc;
      }
    // T = J Rview: dJ = dT Rview^T (only the 4 non-zero J entries matter)
    auto dJ = [&](int r, int c) {
      return GT[r * 3] * cam.R[c * 3] + GT[r * 3 + 1] * cam.R[c * 3 + 1] + GT[r * 3 + 2] * cam.R[c * 3 + 2];
    };
    const D gJ00 = dJ(0, 0), gJ02 = dJ(0, 2), gJ11 = dJ(1, 1), gJ12 = dJ(1, 2);
    // J00 = fx/z, J02 = -fx u/z, J11 = fy/z, J12 = -fy v/z, u = clamp(tx/z), v = clamp(ty/z)
    gt[2] += (-gJ00 * cam.fx + gJ02 * cam.fx * p.u - gJ11 * cam.fy + gJ12 * cam.fy * p.v) * iz2;
    const D gu = -gJ02 * cam.fx * iz, gv = -gJ12 * cam.fy * iz;
    gt[0] = p.u_free ? gt[0] + gu * iz : gt[0];
    gt[2] = p.u_free ? gt[2] - gu * p.t[0] * iz2 : gt[2];
    gt[1] = p.v_free ? gt[1] + gv * iz : gt[1];
    gt[2] = p.v_free ? gt[2] - gv * p.t[1] * iz2 : gt[2];
    // Sig3 = M M^T: dM = (GS + GS^T) M
    D GM[9];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        D acc = splat<D>(0.0);
        for (int k = 0; k < 3; ++k) acc += (GS[i * 3 + k] + GS[k * 3 + i]) * p.M[k * 3 + j];
        GM[i * 3 + j] = acc;
      }
    // M = Rq diag(s): dRq_ij = dM_ij s_j, ds_j = sum_i dM_ij Rq_ij
    D GR[9];
    for (int j = 0; j < 3; ++j) {
      D acc = splat<D>(0.0);
      for (int i = 0; i < 3; ++i) {
        acc += GM[i * 3 + j] * p.Rq[i * 3 + j];
        GR[i * 3 + j] = GM[i * 3 + j] * p.s[j];
      }
      gscale[j] = acc;
    }
    const D w = p.qn[0], x = p.qn[1], y = p.qn[2], zq = p.qn[3];
    const D* G = GR;
    D gq[4];
    gq[0] = 2 * (-zq * G[1] + y * G[2] + zq * G[3] - x * G[5] - y * G[6] + x * G[7]);
    gq[1] = 2 * (y * G[1] + zq * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + zq * G[6] + w * G[7] - 2 * x * G[8]);
    gq[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + zq * G[5] - w * G[6] + zq * G[7] - 2 * y * G[8]);
    gq[3] = 2 * (-2 * zq * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * zq * G[4] + y * G[5] + x * G[6] + y * G[7]);
    // q_hat = q / |q| (constant identity below QUAT_EPS: no gradient)
    const D dot = gq[0] * w + gq[1] * x + gq[2] * y + gq[3] * zq;
    const D iq = 1.0 / p.qnorm;
    for (int i = 0; i < 4; ++i) gquat[i] = p.unit ? (gq[i] - p.qn[i] * dot) * iq : splat<D>(0.0);
  }
  // t = Rview m + tview
  for (int j = 0; j < 3; ++j) gmean[j] = cam.R[j] * gt[0] + cam.R[3 + j] * gt[1] + cam.R[6 + j] * gt[2];
}

// One Gaussian (double): zeros when it was not in depth.
void project_backward_one(const Proj& p, const Camera& cam, const double gconic[3], const double gm2d[2],
                          double gz_depth, double gmean[3], double gquat[4], double gscale[3]) {
  if (!p.in_depth) {
    for (int i = 0; i < 3; ++i) gmean[i] = gscale[i] = 0.0;
    for (int i = 0; i < 4; ++i) gquat[i] = 0.0;
    return;
  }
  project_backward_core(p, cam, gconic, gm2d, gz_depth, p.ok, gmean, gquat, gscale);
}

int clamp_threads(int64_t n) { return int(std::max<int64_t>(1, std::min<int64_t>(n, 256))); }

template <typename S>
std::vector<at::Tensor> forward_impl(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                     const at::Tensor& opac, const at::Tensor& colors, const Camera& cam,
                                     double near, double far, double eps2d, int nthreads) {
  const int64_t N = means.size(0);
  const int D = int(colors.size(1));
  const int W = cam.W, H = cam.H;
  const int tilesX = (W + TILE - 1) / TILE, tilesY = (H + TILE - 1) / TILE;
  auto opts = means.options();
  auto rec = at::zeros({N, REC}, opts);
  auto means2d = at::zeros({N, 2}, opts);
  auto radii = at::zeros({N}, at::kInt);
  auto rect = at::zeros({N, 4}, at::kInt);
  project_all<S>(N, means.data_ptr<S>(), quats.data_ptr<S>(), scales.data_ptr<S>(), opac.data_ptr<S>(), cam,
                 near, far, eps2d, tilesX, tilesY, rec.data_ptr<S>(), means2d.data_ptr<S>(),
                 radii.data_ptr<int32_t>(), rect.data_ptr<int32_t>(), nthreads);
  std::vector<float> depth_f(N);
  const S* r = rec.data_ptr<S>();
  for (int64_t i = 0; i < N; ++i) depth_f[i] = float(r[REC * i + 6]);
  at::Tensor offsets, ids;
  std::tie(offsets, ids) = bin_ordered(depth_order(N, depth_f.data(), radii.data_ptr<int32_t>(), nthreads), r,
                                       rect.data_ptr<int32_t>(), N, W, H, nthreads);
  auto acc = at::empty({H, W, D}, opts);
  auto dn = at::empty({H, W}, opts);
  auto aa = at::empty({H, W}, opts);
  render_forward<S>(cam, D, tilesX, tilesY, rec.data_ptr<S>(), colors.data_ptr<S>(), offsets.data_ptr<int64_t>(),
                    ids.data_ptr<int32_t>(), acc.data_ptr<S>(), dn.data_ptr<S>(), aa.data_ptr<S>(), nthreads);
  return {acc, dn, aa, radii, means2d, rec, offsets, ids};
}

template <typename S>
std::vector<at::Tensor> backward_impl(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                      const at::Tensor& colors, const Camera& cam, double near, double far,
                                      double eps2d, const at::Tensor& rec, const at::Tensor& offsets,
                                      const at::Tensor& ids, const at::Tensor& radii, const at::Tensor& acc,
                                      const at::Tensor& dn, const at::Tensor& aa, const at::Tensor& g_acc,
                                      const at::Tensor& g_dn, const at::Tensor& g_a, const at::Tensor& g_m2d,
                                      int nthreads) {
  const int64_t N = means.size(0);
  const int D = int(colors.size(1));
  const int tilesX = (cam.W + TILE - 1) / TILE, tilesY = (cam.H + TILE - 1) / TILE;
  const int K = G_COL + D;
  auto gbuf = at::empty({nthreads, N, K}, at::kDouble);  // rows valid where ``touched``
  std::vector<uint8_t> touched(size_t(nthreads) * N, 0);
  render_backward<S>(cam, D, tilesX, tilesY, rec.data_ptr<S>(), colors.data_ptr<S>(), offsets.data_ptr<int64_t>(),
                     ids.data_ptr<int32_t>(), acc.data_ptr<S>(), dn.data_ptr<S>(), aa.data_ptr<S>(),
                     g_acc.data_ptr<S>(), g_dn.data_ptr<S>(), g_a.data_ptr<S>(), N, gbuf.data_ptr<double>(),
                     touched.data(), nthreads);
  const double* gb = gbuf.data_ptr<double>();
  auto opts = means.options();
  auto g_means = at::zeros({N, 3}, opts), g_quats = at::zeros({N, 4}, opts), g_scales = at::zeros({N, 3}, opts);
  auto g_opac = at::zeros({N}, opts), g_colors = at::zeros({N, D}, opts), absgrad = at::zeros({N, 2}, opts);
  S *pm = g_means.data_ptr<S>(), *pq = g_quats.data_ptr<S>(), *ps = g_scales.data_ptr<S>();
  S *po = g_opac.data_ptr<S>(), *pc = g_colors.data_ptr<S>(), *pa = absgrad.data_ptr<S>();
  const S* gm2 = g_m2d.data_ptr<S>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  const S *mp = means.data_ptr<S>(), *qp = quats.data_ptr<S>(), *sp = scales.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t i = 0; i < N; ++i) {
    double sum[64 + 16];
    std::vector<double> big;
    double* s = sum;
    if (K > 80) { big.assign(K, 0.0); s = big.data(); }
    for (int k = 0; k < K; ++k) s[k] = 0.0;
    for (int t = 0; t < nthreads; ++t)
      if (touched[size_t(t) * N + i])
        for (int k = 0; k < K; ++k) s[k] += gb[(int64_t(t) * N + i) * K + k];
    const double gext[2] = {double(gm2[2 * i]), double(gm2[2 * i + 1])};
    const bool drawn = rad[i] > 0;
    if (!drawn && gext[0] == 0.0 && gext[1] == 0.0) continue;
    Proj p;
    project_one(mp + 3 * i, qp + 4 * i, sp + 3 * i, cam, near, far, eps2d, p);
    const double gconic[3] = {drawn ? s[G_CA] : 0.0, drawn ? s[G_CB] : 0.0, drawn ? s[G_CC] : 0.0};
    const double gm[2] = {(drawn ? s[G_MX] : 0.0) + gext[0], (drawn ? s[G_MY] : 0.0) + gext[1]};
    double gmean[3], gquat[4], gscale[3];
    project_backward_one(p, cam, gconic, gm, drawn ? s[G_Z] : 0.0, gmean, gquat, gscale);
    for (int k = 0; k < 3; ++k) { pm[3 * i + k] = S(gmean[k]); ps[3 * i + k] = S(gscale[k]); }
    for (int k = 0; k < 4; ++k) pq[4 * i + k] = S(gquat[k]);
    if (drawn) {
      po[i] = S(s[G_OP]);
      for (int c = 0; c < D; ++c) pc[int64_t(i) * D + c] = S(s[G_COL + c]);
      pa[2 * i] = S(s[G_AX]);
      pa[2 * i + 1] = S(s[G_AY]);
    }
  }
  return {g_means, g_quats, g_scales, g_opac, g_colors, absgrad};
}

// ---------------------------------------------------------------------------------------
// True when a Gaussian (world mean, largest scale) cannot reach the image, decided
// without its covariance: out of the depth range, or its projected centre farther outside
// the image than the 3-sigma radius project_all would give it. That radius is
// 3 sqrt(lambda_max) with lambda_max <= |J|_F^2 s_max^2 + eps2d (J the clamped projection
// Jacobian, |R_view| = 1), plus 4 px (project_all's radius exceeds 3 sqrt(lambda_max) by up
// to 1.7 px through its eigenvalue floor and 1 px through ceil); such Gaussians get an empty
// tile rect in project_all, so skipping them changes nothing.
// Decided from the largest log-scale: exp is increasing, and it is taken only for rows in
// the depth range whose centre lies more than 4 px outside the image (the others are kept
// without it). The radius test r < out + 4 is made squared (no square root).
template <typename S>
inline bool off_screen(const S* mean, S max_log_scale, const Camera& cam, double near, double far,
                       double eps2d) {
  const double m[3] = {double(mean[0]), double(mean[1]), double(mean[2])};
  double t[3];
  for (int i = 0; i < 3; ++i)
    t[i] = cam.R[i * 3] * m[0] + cam.R[i * 3 + 1] * m[1] + cam.R[i * 3 + 2] * m[2] + cam.t[i];
  const double z = t[2];
  if (!(z > near && z < far && z > 0.0)) return true;
  const double iz = 1.0 / z, x = t[0] * iz, y = t[1] * iz;
  const double mx = cam.fx * x + cam.cx, my = cam.fy * y + cam.cy;
  if (!std::isfinite(mx) || !std::isfinite(my)) return true;
  // how far the centre lies outside the image, beyond the 4 px margin
  const double out = std::max(std::max(-mx, mx - cam.W), std::max(-my, my - cam.H)) - 4.0;
  if (!(out > 0.0)) return false;
  const double u = std::min(cam.lim_xp, std::max(-cam.lim_xn, x));
  const double v = std::min(cam.lim_yp, std::max(-cam.lim_yn, y));
  const double j2 = (cam.fx * cam.fx * (1.0 + u * u) + cam.fy * cam.fy * (1.0 + v * v)) * (iz * iz);
  const double smax = double(std::exp(max_log_scale));
  const double r2 = 9.0 * (j2 * smax * smax + eps2d);  // (r - 4)^2
  if (!std::isfinite(r2)) return false;  // let the full projection decide
  return r2 < out * out;
}

// ---------------------------------------------------------------------------------------
// Raw Gaussians in groups, for training (autograd: rasterizer.py, _RasterizeGaussiansFn) and
// inference (its forward alone: CpuRasterizer.rasterize_gaussians). One call does what the torch side used to do around the rasterizer: activations (exp of
// log-scales, sigmoid of opacity logits), SH colour seen from the camera centre, rejection of
// Gaussians that cannot reach the image (off_screen), projection, binning and
// compositing; nothing is concatenated. Only the M drawn Gaussians get a record (compacted,
// ``gidx`` maps them back), so the backward's per-thread gradient buffers are M x K instead of
// N x K. The backward goes from the pixel gradients to the raw parameters of every group:
// projection backward, d exp / d sigmoid, and the SH basis times the colour gradient (the
// view direction uses the detached mean, as omnire.gaussians.Gaussians.colors does).

// The 16 real SH basis values (signs included) of omnire.gaussians.eval_sh for unit d:
// colour_c = sum_j b_j coeff_jc, bands above ``degree`` zero.
constexpr double SHD_C0 = 0.28209479177387814, SHD_C1 = 0.4886025119029199;
constexpr double SHD_C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                              0.5462742152960396};
constexpr double SHD_C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                              -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

template <typename S>
inline void sh_basis(int degree, const S d[3], S b[16]) {
  const S x = d[0], y = d[1], z = d[2];
  for (int j = 0; j < 16; ++j) b[j] = S(0);
  b[0] = S(SHD_C0);
  if (degree < 1) return;
  b[1] = -S(SHD_C1) * y; b[2] = S(SHD_C1) * z; b[3] = -S(SHD_C1) * x;
  if (degree < 2) return;
  const S xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b[4] = S(SHD_C2[0]) * xy; b[5] = S(SHD_C2[1]) * yz; b[6] = S(SHD_C2[2]) * (2 * zz - xx - yy);
  b[7] = S(SHD_C2[3]) * xz; b[8] = S(SHD_C2[4]) * (xx - yy);
  if (degree < 3) return;
  b[9] = S(SHD_C3[0]) * y * (3 * xx - yy); b[10] = S(SHD_C3[1]) * xy * z; b[11] = S(SHD_C3[2]) * y * (4 * zz - xx - yy);
  b[12] = S(SHD_C3[3]) * z * (2 * zz - 3 * xx - 3 * yy); b[13] = S(SHD_C3[4]) * x * (4 * zz - xx - yy);
  b[14] = S(SHD_C3[5]) * z * (xx - yy); b[15] = S(SHD_C3[6]) * x * (xx - 3 * yy);
}

// RGB of one Gaussian: colour_c = sum_j b_j coeff_jc over the first ``nb`` bases (j = 0 the DC
// term ``sh0`` (3,), then ``shN`` ((K - 1), 3) row-major), summed in j order, then + 0.5 and
// at least 0 (as Gaussians.colors).
template <typename S>
inline void sh_colour(const S* sh0, const S* shN, const S b[16], int nb, S col[3]) {
  for (int c = 0; c < 3; ++c) {
    S v = b[0] * sh0[c];
    for (int j = 1; j < nb; ++j) v += b[j] * shN[(j - 1) * 3 + c];
    col[c] = std::max(v + S(0.5), S(0));
  }
}

// float: the three channels at once in the lanes of an SSE register (the same products and
// sums per channel, so the same numbers); a NaN stays a NaN (the caller refuses the row).
inline void sh_colour(const float* sh0, const float* shN, const float b[16], int nb, float col[3]) {
  const __m128i rgb = _mm_setr_epi32(-1, -1, -1, 0);  // reads three floats, never past the row
  __m128 v = _mm_mul_ps(_mm_set1_ps(b[0]), _mm_maskload_ps(sh0, rgb));
  for (int j = 1; j < nb; ++j)
    v = _mm_add_ps(v, _mm_mul_ps(_mm_set1_ps(b[j]), _mm_maskload_ps(shN + (j - 1) * 3, rgb)));
  // max(0, x) returns x when x is NaN, and -0 for -0, as std::max(x, 0) does
  v = _mm_max_ps(_mm_setzero_ps(), _mm_add_ps(v, _mm_set1_ps(0.5f)));
  alignas(16) float out[4];
  _mm_store_ps(out, v);
  col[0] = out[0], col[1] = out[1], col[2] = out[2];
}

// sh_colour of n <= 4 rows with bases b[l] and coefficients sh0[l], shN[l] (the same number
// ``nb`` of bases): each row's own operations in its own order (so the same numbers). The
// float version interleaves the rows' sums, four independent chains that overlap in the
// pipeline where one row's sum waits on its previous addition 15 times.
template <typename S>
inline void sh_colours(const S* const sh0[4], const S* const shN[4], const S b[4][16], int nb, int n, S col[4][3]) {
  for (int l = 0; l < n; ++l) sh_colour(sh0[l], shN[l], b[l], nb, col[l]);
}

inline void sh_colours(const float* const sh0[4], const float* const shN[4], const float b[4][16], int nb, int n,
                       float col[4][3]) {
  const __m128i rgb = _mm_setr_epi32(-1, -1, -1, 0);  // reads three floats, never past a row
  const int src[4] = {0, n > 1 ? 1 : 0, n > 2 ? 2 : 0, n > 3 ? 3 : 0};  // spare lanes repeat the first row
  __m128 v[4];
  for (int l = 0; l < 4; ++l) v[l] = _mm_mul_ps(_mm_set1_ps(b[src[l]][0]), _mm_maskload_ps(sh0[src[l]], rgb));
  for (int j = 1; j < nb; ++j)
    for (int l = 0; l < 4; ++l)
      v[l] = _mm_add_ps(v[l], _mm_mul_ps(_mm_set1_ps(b[src[l]][j]), _mm_maskload_ps(shN[src[l]] + (j - 1) * 3, rgb)));
  for (int l = 0; l < n; ++l) {
    // max(0, x) returns x when x is NaN, and -0 for -0, as std::max(x, 0) does
    alignas(16) float out[4];
    _mm_store_ps(out, _mm_max_ps(_mm_setzero_ps(), _mm_add_ps(v[l], _mm_set1_ps(0.5f))));
    col[l][0] = out[0], col[l][1] = out[1], col[l][2] = out[2];
  }
}

// Rows drawn moved by x -> R x + t (a camera-pose correction applied to the Gaussians,
// omnire/camerapose.py, or an actor's box pose placing its box-local Gaussians in the world,
// or both composed; rotations compose as q' = qa q with qa the quaternion of R). Projection
// goes through the recorded camera's view matrix composed with the move (Segment::cam); the
// kernel moves the SH view directions the same way, and the training backward returns the
// gradients of R, t and qa from the rows' own gradients (the moved means' gradient is R
// times the unmoved one's), so no moved copy of the Gaussians exists.
struct Moved {
  bool on = false;
  double R[9], t[3], qa[4];
};

// The camera that sees unmoved rows as ``cam`` sees them moved by ``mv``: view matrix x move.
Camera moved_camera(const Camera& cam, const Moved& mv) {
  if (!mv.on) return cam;
  Camera c = cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j)
      c.R[3 * i + j] = cam.R[3 * i] * mv.R[j] + cam.R[3 * i + 1] * mv.R[3 + j] + cam.R[3 * i + 2] * mv.R[6 + j];
    c.t[i] = cam.R[3 * i] * mv.t[0] + cam.R[3 * i + 1] * mv.t[1] + cam.R[3 * i + 2] * mv.t[2] + cam.t[i];
  }
  return c;
}

// Consecutive rows of one group drawn under one move: group-local rows [begin, end).
struct Segment {
  int64_t group, begin, end;
  Moved mv;
  Camera cam;  // the recorded camera composed with mv
};

// ``seg_rows`` (S,) int64 row counts of consecutive segments covering the groups' rows in
// order (none crossing a group's end), ``moves`` (S,16) float64 [R row-major (9), t (3), qa
// (4)], ``move_on`` (S,) bool (false: drawn unmoved). S = 0: every group one unmoved segment.
std::vector<Segment> make_segments(const std::vector<int64_t>& group_rows, const at::Tensor& seg_rows,
                                   const at::Tensor& moves, const at::Tensor& move_on, const Camera& cam) {
  std::vector<Segment> segs;
  const int64_t S = seg_rows.numel();
  if (S == 0) {
    for (size_t g = 0; g < group_rows.size(); ++g) segs.push_back({int64_t(g), 0, group_rows[g], Moved(), cam});
    return segs;
  }
  TORCH_CHECK(moves.numel() == 16 * S && move_on.numel() == S, "segments: ", S, " row counts need moves (", S,
              ", 16) and move_on (", S, "), got ", moves.numel(), " and ", move_on.numel(), " values");
  auto rows = seg_rows.detach().to(at::kCPU, at::kLong).contiguous();
  auto m = moves.detach().to(at::kCPU, at::kDouble).contiguous();
  auto on = move_on.detach().to(at::kCPU, at::kBool).contiguous();
  const int64_t* r = rows.data_ptr<int64_t>();
  const double* v = m.data_ptr<double>();
  const bool* o = on.data_ptr<bool>();
  size_t g = 0;
  int64_t at_row = 0;
  for (int64_t k = 0; k < S; ++k) {
    while (g < group_rows.size() && at_row == group_rows[g]) { ++g; at_row = 0; }
    TORCH_CHECK(r[k] >= 0 && (r[k] == 0 || (g < group_rows.size() && at_row + r[k] <= group_rows[g])),
                "segments: segment ", k, " (", r[k], " rows) crosses the end of a group or of the rows");
    Segment sg{int64_t(std::min(g, group_rows.size() - 1)), at_row, at_row + r[k], Moved(), cam};
    if (o[k]) {
      sg.mv.on = true;
      for (int i = 0; i < 9; ++i) sg.mv.R[i] = v[16 * k + i];
      for (int i = 0; i < 3; ++i) sg.mv.t[i] = v[16 * k + 9 + i];
      for (int i = 0; i < 4; ++i) sg.mv.qa[i] = v[16 * k + 12 + i];
      sg.cam = moved_camera(cam, sg.mv);
    }
    segs.push_back(sg);
    at_row += r[k];
  }
  while (g < group_rows.size() && at_row == group_rows[g]) { ++g; at_row = 0; }
  TORCH_CHECK(g == group_rows.size(), "segments: the row counts cover fewer rows than the groups hold");
  return segs;
}

// Work units of the per-row loops: up to CHUNK rows of one segment (rows [begin, end) of
// its group), so each unit has one move and one camera.
struct Chunk { int64_t seg, begin, end; };
constexpr int64_t CHUNK = 1024;

std::vector<Chunk> make_chunks(const std::vector<Segment>& segs) {
  std::vector<Chunk> chunks;
  for (size_t k = 0; k < segs.size(); ++k)
    for (int64_t b = segs[k].begin; b < segs[k].end; b += CHUNK)
      chunks.push_back({int64_t(k), b, std::min(segs[k].end, b + CHUNK)});
  return chunks;
}

// Unit view direction from the camera centre to ``mean`` (moved by ``mv`` when on),
// normalised as Gaussians.colors does.
template <typename S>
inline void view_dir(const S* mean, const double center[3], const Moved& mv, S d[3]) {
  if (mv.on) {
    for (int j = 0; j < 3; ++j)
      d[j] = S(mv.R[3 * j] * double(mean[0]) + mv.R[3 * j + 1] * double(mean[1]) + mv.R[3 * j + 2] * double(mean[2]) +
               mv.t[j] - center[j]);
  } else {
    for (int j = 0; j < 3; ++j) d[j] = S(mean[j] - S(center[j]));
  }
  const S nrm = std::max(S(std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])), S(1e-8));
  for (int j = 0; j < 3; ++j) d[j] = d[j] / nrm;
}

// Gradient of qa from one row: q' = qa q, so dL/dq' = L(qa) g (g = dL/dq, L(qa) the
// orthogonal left-multiplication matrix of the unit qa) and dL/dqa = Rm(q)^T dL/dq' (Rm(q)
// the right-multiplication matrix: qa q = Rm(q) qa). Quaternions (w, x, y, z).
inline void qa_gradient(const double qa[4], const double q[4], const double g[4], double out[4]) {
  const double a0 = qa[0], a1 = qa[1], a2 = qa[2], a3 = qa[3];
  const double p[4] = {a0 * g[0] - a1 * g[1] - a2 * g[2] - a3 * g[3],
                       a1 * g[0] + a0 * g[1] - a3 * g[2] + a2 * g[3],
                       a2 * g[0] + a3 * g[1] + a0 * g[2] - a1 * g[3],
                       a3 * g[0] - a2 * g[1] + a1 * g[2] + a0 * g[3]};
  const double b0 = q[0], b1 = q[1], b2 = q[2], b3 = q[3];
  // Rm(q) = [[b0,-b1,-b2,-b3],[b1,b0,b3,-b2],[b2,-b3,b0,b1],[b3,b2,-b1,b0]]; out = Rm^T p
  out[0] = b0 * p[0] + b1 * p[1] + b2 * p[2] + b3 * p[3];
  out[1] = -b1 * p[0] + b0 * p[1] - b3 * p[2] + b2 * p[3];
  out[2] = -b2 * p[0] + b3 * p[1] + b0 * p[2] - b1 * p[3];
  out[3] = -b3 * p[0] - b2 * p[1] + b1 * p[2] + b0 * p[3];
}

template <typename S>
inline S sigmoid_of(S x) { return S(1) / (S(1) + std::exp(-x)); }

// The gradients of drawn rows' means, quaternions and scales (not log-scales) from those of
// their conics, 2D means and depths: project_one then project_backward_one without the
// exits a drawn row never takes (it is in depth and its conic is defined), so that four rows
// can share the lanes of D4.
template <typename D>
void drawn_row_gradients(const D mean[3], const D quat[4], const D scale[3], const Camera& cam, double eps2d,
                         const D gconic[3], const D gm2d[2], D gz_depth, D gmean[3], D gquat[4], D gscale[3]) {
  ProjCore<D> p;
  for (int i = 0; i < 3; ++i)
    p.t[i] = cam.R[i * 3] * mean[0] + cam.R[i * 3 + 1] * mean[1] + cam.R[i * 3 + 2] * mean[2] + cam.t[i];
  project_core(quat, scale, 1.0 / p.t[2], cam, eps2d, p);
  project_backward_core(p, cam, gconic, gm2d, gz_depth, true, gmean, gquat, gscale);
}

// One group of raw Gaussians: row-major pointers, its row count, SH bases beyond the DC
// term (K1 = (deg + 1)^2 - 1) and the bands used (min(deg, requested)).
template <typename S>
struct RawGroup {
  const S *means, *quats, *scales, *opac, *sh0, *shN;
  int64_t n, start;
  int K1, deg;
};

// ``spans``: per group (first row, rows) of its tensors (check_groups).
template <typename S>
std::vector<RawGroup<S>> raw_groups(const std::vector<at::Tensor>& means, const std::vector<at::Tensor>& quats,
                                    const std::vector<at::Tensor>& scales, const std::vector<at::Tensor>& opac,
                                    const std::vector<at::Tensor>& sh0, const std::vector<at::Tensor>& shN,
                                    const std::vector<std::pair<int64_t, int64_t>>& spans, int sh_degree) {
  std::vector<RawGroup<S>> gs(means.size());
  int64_t start = 0;
  for (size_t g = 0; g < means.size(); ++g) {
    RawGroup<S>& r = gs[g];
    const int64_t f = spans[g].first;
    r.K1 = int(shN[g].size(1));
    r.means = means[g].data_ptr<S>() + 3 * f; r.quats = quats[g].data_ptr<S>() + 4 * f;
    r.scales = scales[g].data_ptr<S>() + 3 * f; r.opac = opac[g].data_ptr<S>() + f;
    r.sh0 = sh0[g].data_ptr<S>() + 3 * f; r.shN = shN[g].data_ptr<S>() + int64_t(r.K1) * 3 * f;
    r.n = spans[g].second;
    r.start = start;
    start += r.n;
    int deg = 0;
    while ((deg + 1) * (deg + 1) - 1 < r.K1) ++deg;
    r.deg = std::min(deg, sh_degree);
  }
  return gs;
}

// A drawn row's scratch as the per-row loop writes it: record, colour, tile rect (tile
// indices, checked below 65536) and row, in one 64-byte line for float (the depth-order
// gather reads one line per Gaussian, in an order scattered over all of them).
template <typename S>
struct alignas(64) DrawnSlot {
  S rec[REC];
  S col[3];
  uint16_t rect[4];
  int32_t row;
};
static_assert(sizeof(DrawnSlot<float>) == 64, "one cache line per drawn float row");

template <typename S>
std::vector<at::Tensor> forward_train_impl(const std::vector<RawGroup<S>>& groups, int64_t N, const double center[3],
                                           const std::vector<Segment>& segs, const Camera& cam, double near, double far,
                                           double eps2d, bool cull, at::ScalarType st, int nthreads) {
  const int W = cam.W, H = cam.H;
  const int tilesX = (W + TILE - 1) / TILE, tilesY = (H + TILE - 1) / TILE;
  TORCH_CHECK(tilesX < 65536 && tilesY < 65536, "image of ", W, " x ", H, " pixels: at most 65535 tiles per side");
  TORCH_CHECK(N < (int64_t(1) << 31), N, " Gaussians: at most 2^31 - 1");
  auto opts = at::TensorOptions().dtype(st);
  // Per-Gaussian scratch, packed per chunk: the j-th drawn row of a chunk whose first row is
  // k0 writes slot k0 + j (its row in the slot), so the depth-order gather below reads a few
  // dense runs instead of rows scattered over all N. Left uninitialised: only drawn slots are read.
  std::unique_ptr<DrawnSlot<S>[]> slots(new DrawnSlot<S>[size_t(std::max<int64_t>(N, 1))]);
  // beside each drawn slot its sort item (depth bits, slot), so that the depth order reads
  // 8 bytes per drawn row instead of its slot's line
  std::unique_ptr<uint64_t[]> items(new uint64_t[size_t(std::max<int64_t>(N, 1))]);
  auto radii = at::empty({N}, at::kInt);
  auto means2d = at::empty({N, 2}, opts);
  int32_t* radp = radii.data_ptr<int32_t>();
  S* m2p = means2d.data_ptr<S>();
  const std::vector<Chunk> chunks = make_chunks(segs);
  std::vector<int64_t> drawn(chunks.size(), 0);  // drawn rows per chunk
  int64_t bad = std::numeric_limits<int64_t>::max();
  int64_t rejected = 0;
  // wall seconds of the stages (returned for profiles): rows (culling, activation,
  // projection, SH colour), depth order (sort and gather), tile binning, compositing
  auto stages = at::zeros({4}, at::kDouble);
  double* stage_s = stages.data_ptr<double>();
  double clock = omp_get_wtime();
  auto lap = [&](int k) {
    const double now = omp_get_wtime();
    stage_s[k] = now - clock;
    clock = now;
  };
  // Dynamic chunks: a culled row costs a few ns, a drawn one its projection and SH colour;
  // each row writes only its own outputs, so the schedule changes no result.
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads) reduction(min : bad) reduction(+ : rejected)
  for (size_t ci = 0; ci < chunks.size(); ++ci) {
    const Segment& sg = segs[chunks[ci].seg];
    const RawGroup<S>& G = groups[sg.group];
    const int64_t k0 = G.start + chunks[ci].begin;
    int64_t n_drawn = 0;
    // A projected row's record, rect and colour ``c`` (sh_colours), in row order (slots follow rows).
    auto finish = [&](int64_t i, const Proj& p, const S c[3]) {
      const int64_t k = G.start + i;
      if (p.in_depth) { m2p[2 * k] = S(p.m2d[0]); m2p[2 * k + 1] = S(p.m2d[1]); }
      if (!p.ok) return;
      const S o = sigmoid_of(G.opac[i]);
      double r;
      DrawnSlot<S>& slot = slots[k0 + n_drawn];  // kept only if the row is drawn
      int32_t rc[4];
      if (!radius_rect(p, tilesX, tilesY, &r, rc) || !(double(o) > 0.0)) return;
      S* col = slot.col;
      for (int j = 0; j < 3; ++j) col[j] = c[j];
      if (!(std::isfinite(double(col[0])) && std::isfinite(double(col[1])) && std::isfinite(double(col[2])))) {
        bad = std::min(bad, k);
        return;
      }
      radp[k] = int32_t(r);
      write_record(p, double(o), tilesX, tilesY, slot.rec, rc);
      for (int j = 0; j < 4; ++j) slot.rect[j] = uint16_t(rc[j]);
      slot.row = int32_t(k);
      const float depth = float(slot.rec[6]);
      uint32_t bits;
      std::memcpy(&bits, &depth, 4);
      items[k0 + n_drawn] = (uint64_t(bits) << 32) | uint64_t(uint32_t(k0 + n_drawn));
      ++n_drawn;
    };
    // Rows past the culling wait in fours: their projections share the lanes of D4
    // (project_four, project_one's numbers) and their SH colours are summed together
    // (sh_colours), then each finishes in row order. A row that is not drawn after all
    // has its colour computed for nothing (few: nearly every row kept is drawn).
    int64_t pend[4];
    const S* pmean[4];
    const S* pquat[4];
    S pscale[4][3];
    int npend = 0;
    const int nb = (G.deg + 1) * (G.deg + 1);
    auto flush = [&]() {
      if (npend == 0) return;
      Proj p[4];
      project_four(pmean, pquat, pscale, npend, sg.cam, near, far, eps2d, p);
      S b[4][16], col[4][3], d[3];
      const S* psh0[4];
      const S* pshN[4];
      for (int l = 0; l < npend; ++l) {
        view_dir(pmean[l], center, sg.mv, d);
        sh_basis(G.deg, d, b[l]);
        psh0[l] = G.sh0 + 3 * pend[l];
        pshN[l] = G.shN + int64_t(G.K1) * 3 * pend[l];
      }
      sh_colours(psh0, pshN, b, nb, npend, col);
      for (int l = 0; l < npend; ++l) finish(pend[l], p[l], col[l]);
      npend = 0;
    };
    for (int64_t i = chunks[ci].begin; i < chunks[ci].end; ++i) {
      const int64_t k = G.start + i;
      const S *mp = G.means + 3 * i, *qp = G.quats + 4 * i, *sp = G.scales + 3 * i;
      radp[k] = 0;
      m2p[2 * k] = m2p[2 * k + 1] = S(0);
      // every value finite <=> their sum in double is (14 floats cannot overflow a double;
      // an infinity or NaN makes the sum infinite or NaN); four independent partial sums
      const S* c0 = G.sh0 + 3 * i;
      const double sum = ((double(G.opac[i]) + double(mp[0])) + (double(mp[1]) + double(mp[2]))) +
                         ((double(sp[0]) + double(sp[1])) + (double(sp[2]) + double(c0[0]))) +
                         ((double(c0[1]) + double(c0[2])) + (double(qp[0]) + double(qp[1]))) +
                         (double(qp[2]) + double(qp[3]));
      if (!std::isfinite(sum)) { bad = std::min(bad, k); continue; }
      // the three scales are only needed for Gaussians that pass the culling
      if (cull && off_screen(mp, std::max({sp[0], sp[1], sp[2]}), sg.cam, near, far, eps2d)) {
        ++rejected;
        continue;
      }
      const int l = npend++;
      pend[l] = i;
      pmean[l] = mp;
      pquat[l] = qp;
      for (int j = 0; j < 3; ++j) pscale[l][j] = std::exp(sp[j]);
      if (npend == 4) flush();
    }
    flush();
    drawn[ci] = n_drawn;
  }
  const int64_t first_bad = bad != std::numeric_limits<int64_t>::max() ? bad : -1;
  if (first_bad >= 0) {
    auto e = at::zeros({0}, opts);
    return {e, e, e, at::zeros({0}, at::kInt), e, e, e, at::zeros({0}, at::kLong), at::zeros({1}, at::kLong),
            at::zeros({0}, at::kInt), at::full({1}, first_bad, at::kLong), at::zeros({1}, at::kLong), stages};
  }
  lap(0);
  // Compact the drawn Gaussians in front-to-back order (ties by row, so deterministic: slots
  // increase with rows): each tile list then walks the records, and the backward its
  // gradient rows, in increasing address order instead of jumping across the whole array.
  std::vector<uint64_t> order;
  {
    int64_t total = 0;
    for (int64_t n : drawn) total += n;
    order.reserve(total);
    for (size_t ci = 0; ci < chunks.size(); ++ci) {
      const int64_t k0 = groups[segs[chunks[ci].seg].group].start + chunks[ci].begin;
      order.insert(order.end(), items.get() + k0, items.get() + k0 + drawn[ci]);
    }
    sort_by_depth(order, nthreads);
  }
  const int64_t M = int64_t(order.size());
  auto gidx = at::empty({M}, at::kLong);
  int64_t* gi = gidx.data_ptr<int64_t>();
  auto rec = at::empty({M, REC}, opts);
  auto col = at::empty({M, 3}, opts);
  std::vector<int32_t> rect_c(4 * M);
  S* rc = rec.data_ptr<S>();
  S* cc = col.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t m = 0; m < M; ++m) {
    const DrawnSlot<S>& slot = slots[int64_t(order[m] & 0xFFFFFFFFu)];
    if (m + 16 < M) {  // slots are read in depth order, i.e. scattered: fetch ahead
      const DrawnSlot<S>* ahead = &slots[int64_t(order[m + 16] & 0xFFFFFFFFu)];
      for (size_t line = 0; line < sizeof(DrawnSlot<S>); line += 64)
        __builtin_prefetch(reinterpret_cast<const char*>(ahead) + line);
    }
    gi[m] = slot.row;
    for (int j = 0; j < REC; ++j) rc[REC * m + j] = slot.rec[j];
    for (int j = 0; j < 3; ++j) cc[3 * m + j] = slot.col[j];
    for (int j = 0; j < 4; ++j) rect_c[4 * m + j] = slot.rect[j];
    order[m] = (order[m] & ~uint64_t(0xFFFFFFFFu)) | uint64_t(uint32_t(m));  // now indexes the records
  }
  lap(1);
  at::Tensor offsets, ids;
  std::tie(offsets, ids) = bin_ordered(order, rc, rect_c.data(), M, W, H, nthreads);
  lap(2);
  auto acc = at::empty({H, W, 3}, opts);
  auto dn = at::empty({H, W}, opts);
  auto aa = at::empty({H, W}, opts);
  render_forward<S>(cam, 3, tilesX, tilesY, rc, cc, offsets.data_ptr<int64_t>(), ids.data_ptr<int32_t>(),
                    acc.data_ptr<S>(), dn.data_ptr<S>(), aa.data_ptr<S>(), nthreads);
  lap(3);
  return {acc, dn, aa, radii, means2d, rec, col, gidx, offsets, ids, at::full({1}, -1, at::kLong),
          at::full({1}, N - rejected, at::kLong), stages};
}

template <typename S>
std::vector<at::Tensor> backward_train_impl(const std::vector<RawGroup<S>>& groups, const std::vector<int64_t>& block,
                                            int64_t N, const double center[3], const std::vector<Segment>& segs,
                                            const Camera& cam,
                                            double eps2d, const at::Tensor& rec, const at::Tensor& col,
                                            const at::Tensor& gidx, const at::Tensor& offsets, const at::Tensor& ids,
                                            const at::Tensor& acc, const at::Tensor& dn, const at::Tensor& aa,
                                            const at::Tensor& g_acc, const at::Tensor& g_dn, const at::Tensor& g_a,
                                            at::ScalarType st, int nthreads) {
  const int64_t M = gidx.size(0);
  const int tilesX = (cam.W + TILE - 1) / TILE, tilesY = (cam.H + TILE - 1) / TILE;
  const int K = G_COL + 3;
  auto gbuf = at::empty({nthreads, M, K}, at::kDouble);  // rows valid where ``touched``
  std::vector<uint8_t> touched(size_t(nthreads) * M, 0);
  render_backward<S>(cam, 3, tilesX, tilesY, rec.data_ptr<S>(), col.data_ptr<S>(), offsets.data_ptr<int64_t>(),
                     ids.data_ptr<int32_t>(), acc.data_ptr<S>(), dn.data_ptr<S>(), aa.data_ptr<S>(),
                     g_acc.data_ptr<S>(), g_dn.data_ptr<S>(), g_a.data_ptr<S>(), M, gbuf.data_ptr<double>(),
                     touched.data(), nthreads);
  auto opts = at::TensorOptions().dtype(st);
  // Outputs: per group the gradients of means, quats, log-scales, opacity logits, sh0 and shN
  // (undefined, i.e. None, when the group uses no band above 0: its shN took no part, as in
  // Gaussians.colors, and an optimiser must not see a zero gradient for it); then AbsGrad
  // (N, 2). Every row is written exactly once (zeros where nothing was drawn), so the
  // tensors start uninitialised: no separate memset of the N-row outputs.
  // Consecutive groups of one block (``block``, non-decreasing; e.g. the segments of one
  // node's parameters drawn without a copy) write their rows into one set of tensors.
  std::vector<at::Tensor> out;
  const size_t NG = groups.size();
  std::vector<S*> gm(NG), gq(NG), gs(NG), go(NG), g0(NG), gn(NG);
  for (size_t first = 0; first < NG;) {
    size_t last = first + 1;
    while (last < NG && block[last] == block[first]) ++last;
    int64_t n = 0;
    for (size_t g = first; g < last; ++g) {
      TORCH_CHECK(groups[g].K1 == groups[first].K1 && groups[g].deg == groups[first].deg,
                  "groups of one block need one SH layout");
      n += groups[g].n;
    }
    const int K1 = groups[first].K1;
    out.push_back(at::empty({n, 3}, opts)); S* bm = out.back().data_ptr<S>();
    out.push_back(at::empty({n, 4}, opts)); S* bq = out.back().data_ptr<S>();
    out.push_back(at::empty({n, 3}, opts)); S* bs = out.back().data_ptr<S>();
    out.push_back(at::empty({n}, opts)); S* bo = out.back().data_ptr<S>();
    out.push_back(at::empty({n, 1, 3}, opts)); S* b0 = out.back().data_ptr<S>();
    S* bn = nullptr;
    if (groups[first].deg > 0) {
      out.push_back(at::empty({n, K1, 3}, opts)); bn = out.back().data_ptr<S>();
    } else {
      out.push_back(at::Tensor());
    }
    int64_t r = 0;  // first row of group g in the block
    for (size_t g = first; g < last; r += groups[g].n, ++g) {
      gm[g] = bm + 3 * r; gq[g] = bq + 4 * r; gs[g] = bs + 3 * r; go[g] = bo + r; g0[g] = b0 + 3 * r;
      gn[g] = bn ? bn + int64_t(K1) * 3 * r : nullptr;
    }
    first = last;
  }
  auto absgrad = at::empty({N, 2}, opts);
  S* pa = absgrad.data_ptr<S>();
  double* gbw = gbuf.data_ptr<double>();
  // Sum the threads' buffers into the first, streaming in record order: the loop below then
  // reads one row per Gaussian at its record slot (depth order) instead of one per thread.
  // Rows a thread never touched hold garbage and are skipped; untouched everywhere: zeros.
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t m = 0; m < M; ++m) {
    double* dst = gbw + m * K;
    bool have = touched[size_t(m)];
    for (int t = 1; t < nthreads; ++t) {
      if (!touched[size_t(t) * M + m]) continue;
      const double* src = gbw + (int64_t(t) * M + m) * K;
      for (int k = 0; k < K; ++k) dst[k] = have ? dst[k] + src[k] : src[k];
      have = true;
    }
    if (!have) std::fill_n(dst, K, 0.0);
  }
  const double* gb = gbw;
  const int64_t* gi = gidx.data_ptr<int64_t>();
  const S* cc = col.data_ptr<S>();
  // record slot of each row (-1: not drawn)
  std::vector<int64_t> slot(N, -1);
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t m = 0; m < M; ++m) slot[gi[m]] = m;  // gi is a permutation: no two writes collide
  // Gradients of each segment's move (Moved): per chunk of rows [sum g_mean x^T (9), sum
  // g_mean (3), sum dL/dqa (4)], summed over each segment's chunks in order afterwards, so
  // the result does not depend on which thread took which chunk.
  const std::vector<Chunk> chunks = make_chunks(segs);
  bool any_move = false;
  for (const Segment& sg : segs) any_move = any_move || sg.mv.on;
  std::vector<double> move_sums(any_move ? 16 * chunks.size() : 0, 0.0);
  // Dynamic chunks of rows, as in forward_train_impl (no result depends on them).
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
  for (size_t ci = 0; ci < chunks.size(); ++ci) {
    const Segment& sg = segs[chunks[ci].seg];
    const Moved& mv = sg.mv;
    const size_t g = size_t(sg.group);
    const RawGroup<S>& G = groups[g];
    const int nbN = G.deg > 0 ? G.K1 : 0;  // shN rows written (all of them, bands above deg zero)
    // A drawn row's gradients once those of its mean, quaternion and scales are known.
    // sc: the row's scales (exp of its log-scales), as drawn_row_gradients took them.
    auto finish_row = [&](int64_t i, const double* s, const double sc[3], const double gmean[3],
                          const double gquat[4], const double gscale[3]) {
      const int64_t k = G.start + i, m = slot[k];
      const S *mp = G.means + 3 * i, *qp = G.quats + 4 * i;
      for (int j = 0; j < 3; ++j) {
        gm[g][3 * i + j] = S(gmean[j]);
        gs[g][3 * i + j] = S(gscale[j] * sc[j]);  // d exp(x) / dx = exp(x)
      }
      for (int j = 0; j < 4; ++j) gq[g][4 * i + j] = S(gquat[j]);
      const double o = double(sigmoid_of(G.opac[i]));
      go[g][i] = S(s[G_OP] * o * (1.0 - o));
      S d[3], b[16];
      if (mv.on) {
        double* ms = move_sums.data() + 16 * ci;
        const double q[4] = {double(qp[0]), double(qp[1]), double(qp[2]), double(qp[3])};
        double gqa[4];
        qa_gradient(mv.qa, q, gquat, gqa);
        for (int r = 0; r < 3; ++r) {
          for (int j = 0; j < 3; ++j) ms[3 * r + j] += gmean[r] * double(mp[j]);
          ms[9 + r] += gmean[r];
        }
        for (int j = 0; j < 4; ++j) ms[12 + j] += gqa[j];
      }
      view_dir(mp, center, mv, d);  // the detached mean: no gradient through the direction
      sh_basis(G.deg, d, b);     // bands above deg are 0: their coefficients get 0
      for (int c = 0; c < 3; ++c) {
        // colour clamped at 0: no gradient (clamp_min's)
        const S gc = cc[3 * m + c] > S(0) ? S(s[G_COL + c]) : S(0);
        g0[g][3 * i + c] = b[0] * gc;
        for (int j = 1; j <= nbN; ++j) gn[g][(int64_t(G.K1) * i + (j - 1)) * 3 + c] = b[j] * gc;
      }
      pa[2 * k] = S(s[G_AX]);
      pa[2 * k + 1] = S(s[G_AY]);
    };
    // Drawn rows wait in fours: the projection's gradient runs on the four lanes of an AVX2
    // register (drawn_row_gradients, the same numbers as one row at a time), then each row
    // finishes in row order (the move sums add up in the same order).
    int64_t batch[4];
    double bs[4][G_COL + 3];
    int nbatch = 0;
    auto flush = [&]() {
      if (nbatch == 0) return;
      D4 mean[3], quat[4], scale[3], gconic[3], gm2[2], gz, gmean[3], gquat[4], gscale[3];
      for (int l = 0; l < 4; ++l) {
        const int src = l < nbatch ? l : 0;  // spare lanes repeat the first row
        const int64_t i = batch[src];
        const double* s = bs[src];
        for (int j = 0; j < 3; ++j) {
          mean[j][l] = double(G.means[3 * i + j]);
          scale[j][l] = double(S(std::exp(G.scales[3 * i + j])));
        }
        for (int j = 0; j < 4; ++j) quat[j][l] = double(G.quats[4 * i + j]);
        gconic[0][l] = s[G_CA]; gconic[1][l] = s[G_CB]; gconic[2][l] = s[G_CC];
        gm2[0][l] = s[G_MX]; gm2[1][l] = s[G_MY];
        gz[l] = s[G_Z];
      }
      drawn_row_gradients(mean, quat, scale, sg.cam, eps2d, gconic, gm2, gz, gmean, gquat, gscale);
      for (int l = 0; l < nbatch; ++l) {
        const double rm[3] = {gmean[0][l], gmean[1][l], gmean[2][l]};
        const double rq[4] = {gquat[0][l], gquat[1][l], gquat[2][l], gquat[3][l]};
        const double rs[3] = {gscale[0][l], gscale[1][l], gscale[2][l]};
        const double rsc[3] = {scale[0][l], scale[1][l], scale[2][l]};
        finish_row(batch[l], bs[l], rsc, rm, rq, rs);
      }
      nbatch = 0;
    };
    for (int64_t i = chunks[ci].begin; i < chunks[ci].end; ++i) {
      const int64_t k = G.start + i;
      const int64_t m = slot[k];
      // Records are in depth order, rows in row order: fetch a later row's sums ahead, the
      // work per row is too long for the CPU to overlap these misses by itself.
      if (i + 16 < G.n) {
        const int64_t ma = slot[k + 16];
        if (ma >= 0) {
          __builtin_prefetch(gb + ma * K);
          __builtin_prefetch(gb + ma * K + 8);
        }
      }
      if (m < 0) {  // a run of rows not drawn: their gradients are 0, written array by array
        int64_t e = i + 1;
        while (e < chunks[ci].end && slot[G.start + e] < 0) ++e;
        const int64_t n = e - i;
        std::fill_n(gm[g] + 3 * i, 3 * n, S(0));
        std::fill_n(gs[g] + 3 * i, 3 * n, S(0));
        std::fill_n(g0[g] + 3 * i, 3 * n, S(0));
        std::fill_n(gq[g] + 4 * i, 4 * n, S(0));
        std::fill_n(go[g] + i, n, S(0));
        if (nbN > 0) std::fill_n(gn[g] + 3 * int64_t(nbN) * i, 3 * int64_t(nbN) * n, S(0));
        std::fill_n(pa + 2 * k, 2 * n, S(0));
        i = e - 1;
        continue;
      }
      batch[nbatch] = i;
      for (int q = 0; q < K; ++q) bs[nbatch][q] = gb[m * K + q];
      if (++nbatch == 4) flush();
    }
    flush();
  }
  out.push_back(absgrad);
  if (any_move) {  // per segment [sum_rows g_mean x^T (3x3 row-major), sum_rows g_mean (3), dL/dqa (4)], unmoved frame
    auto sums = at::zeros({int64_t(segs.size()), 16}, at::kDouble);
    double* sp = sums.data_ptr<double>();
    for (size_t ci = 0; ci < chunks.size(); ++ci)
      for (int j = 0; j < 16; ++j) sp[16 * chunks[ci].seg + j] += move_sums[16 * ci + j];
    out.push_back(sums);
  }
  return out;
}

void check_cpu_contig(const at::Tensor& t, at::ScalarType st, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.scalar_type() == st, name, " has dtype ", t.scalar_type(), ", expected ", st);
}

}  // namespace

// Returns [acc (H,W,D), depth numerator (H,W), alpha (H,W), radii (N,) int32, means2d (N,2),
//          records (N,9), tile offsets (ntiles+1,) int64, tile ids (M,) int32].
std::vector<at::Tensor> raster_forward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opac,
                                       at::Tensor colors, at::Tensor viewmat, at::Tensor K, int64_t width,
                                       int64_t height, double near, double far, double eps2d, int64_t nthreads) {
  const auto st = means.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "means must be float32 or float64");
  for (auto [t, n] : {std::pair{&means, "means"}, {&quats, "quats"}, {&scales, "scales"}, {&opac, "opacities"},
                      {&colors, "colors"}})
    check_cpu_contig(*t, st, n);
  const Camera cam = make_camera(viewmat, K, int(width), int(height));
  const int nt = clamp_threads(nthreads);
  if (st == at::kFloat) return forward_impl<float>(means, quats, scales, opac, colors, cam, near, far, eps2d, nt);
  return forward_impl<double>(means, quats, scales, opac, colors, cam, near, far, eps2d, nt);
}

// Returns [g_means (N,3), g_quats (N,4), g_scales (N,3), g_opacities (N,), g_colors (N,D), absgrad2d (N,2)].
std::vector<at::Tensor> raster_backward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor colors,
                                        at::Tensor viewmat, at::Tensor K, int64_t width, int64_t height, double near,
                                        double far, double eps2d, at::Tensor rec, at::Tensor offsets, at::Tensor ids,
                                        at::Tensor radii, at::Tensor acc, at::Tensor dn, at::Tensor aa,
                                        at::Tensor g_acc, at::Tensor g_dn, at::Tensor g_a, at::Tensor g_m2d,
                                        int64_t nthreads) {
  const auto st = means.scalar_type();
  for (auto [t, n] : {std::pair{&means, "means"}, {&quats, "quats"}, {&scales, "scales"}, {&colors, "colors"},
                      {&rec, "rec"}, {&acc, "acc"}, {&dn, "dn"}, {&aa, "alpha"}, {&g_acc, "g_acc"},
                      {&g_dn, "g_dn"}, {&g_a, "g_alpha"}, {&g_m2d, "g_means2d"}})
    check_cpu_contig(*t, st, n);
  const Camera cam = make_camera(viewmat, K, int(width), int(height));
  const int nt = clamp_threads(nthreads);
  if (st == at::kFloat)
    return backward_impl<float>(means, quats, scales, colors, cam, near, far, eps2d, rec, offsets, ids, radii, acc,
                                dn, aa, g_acc, g_dn, g_a, g_m2d, nt);
  return backward_impl<double>(means, quats, scales, colors, cam, near, far, eps2d, rec, offsets, ids, radii, acc,
                               dn, aa, g_acc, g_dn, g_a, g_m2d, nt);
}

// Training path (see forward_train_impl): raw groups means (N_g,3), quats (N_g,4), log-scales
// (N_g,3), opacity logits (N_g,), sh0 (N_g,1,3), shN (N_g,K_g,3), one dtype (float32 or float64),
// contiguous. Returns [acc (H,W,3), depth numerator (H,W), alpha (H,W), radii (N,) int32,
// means2d (N,2), records (M,REC), colours (M,3), drawn rows (M,) int64, tile offsets, tile ids,
// first non-finite row (1,) or -1 (then nothing else is computed), Gaussians not culled (1,),
// wall seconds of its stages (4,) float64: rows, depth order, binning, compositing].
// ``seg_rows``, ``moves``, ``move_on``: the rows' moves (make_segments); ``viewmat`` is the
// recorded camera's.
//
// ``group_spans`` (G,2) int64: per group, the first row and the number of rows of its tensors
// it draws (e.g. one actor's rows of a node's parameters, no copy); empty: all rows. Returns
// the spans.
static std::vector<std::pair<int64_t, int64_t>> check_groups(
    const std::vector<at::Tensor>& means, const std::vector<at::Tensor>& quats, const std::vector<at::Tensor>& scales,
    const std::vector<at::Tensor>& opac, const std::vector<at::Tensor>& sh0, const std::vector<at::Tensor>& shN,
    const at::Tensor& group_spans, at::ScalarType st) {
  const size_t G = means.size();
  TORCH_CHECK(quats.size() == G && scales.size() == G && opac.size() == G && sh0.size() == G && shN.size() == G,
              "every parameter needs one tensor per group");
  std::vector<std::pair<int64_t, int64_t>> spans(G);
  if (group_spans.numel() == 0) {
    for (size_t g = 0; g < G; ++g) spans[g] = {0, means[g].size(0)};
  } else {
    TORCH_CHECK(group_spans.numel() == int64_t(2 * G), "group_spans: (", G, ", 2) expected, got ", group_spans.numel(),
                " values");
    auto sp = group_spans.detach().to(at::kCPU, at::kLong).contiguous();
    for (size_t g = 0; g < G; ++g) {
      spans[g] = {sp.data_ptr<int64_t>()[2 * g], sp.data_ptr<int64_t>()[2 * g + 1]};
      TORCH_CHECK(spans[g].first >= 0 && spans[g].second >= 0 && spans[g].first + spans[g].second <= means[g].size(0),
                  "group ", g, ": rows ", spans[g].first, " + ", spans[g].second, " outside its ", means[g].size(0),
                  " rows");
    }
  }
  for (size_t g = 0; g < G; ++g) {
    const int64_t n = means[g].size(0);
    for (auto [t, name] : {std::pair{&means[g], "means"}, {&quats[g], "quats"}, {&scales[g], "scales"},
                           {&opac[g], "opacities"}, {&sh0[g], "sh0"}, {&shN[g], "shN"}}) {
      check_cpu_contig(*t, st, name);
      TORCH_CHECK(t->size(0) == n, name, " of group ", g, " has ", t->size(0), " rows, expected ", n);
    }
    TORCH_CHECK(means[g].dim() == 2 && means[g].size(1) == 3 && quats[g].dim() == 2 && quats[g].size(1) == 4 &&
                    scales[g].dim() == 2 && scales[g].size(1) == 3 && opac[g].dim() == 1,
                "means (N,3), quats (N,4), scales (N,3), opacities (N,)");
    TORCH_CHECK(shN[g].dim() == 3 && shN[g].size(2) == 3 && shN[g].size(1) <= 15 && sh0[g].numel() == 3 * n,
                "sh0 (N,1,3) / shN (N,K,3) with K <= 15");
  }
  return spans;
}

std::vector<at::Tensor> raster_forward_train(std::vector<at::Tensor> means, std::vector<at::Tensor> quats,
                                             std::vector<at::Tensor> scales, std::vector<at::Tensor> opac,
                                             std::vector<at::Tensor> sh0, std::vector<at::Tensor> shN,
                                             at::Tensor group_spans, int64_t sh_degree, at::Tensor center,
                                             at::Tensor seg_rows, at::Tensor moves, at::Tensor move_on,
                                             at::Tensor viewmat, at::Tensor K, int64_t width, int64_t height,
                                             double near, double far, double eps2d, bool cull, int64_t nthreads) {
  TORCH_CHECK(!means.empty(), "at least one group");
  const auto st = means[0].scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "float32 or float64 Gaussians");
  const auto spans = check_groups(means, quats, scales, opac, sh0, shN, group_spans, st);
  auto c = center.detach().to(at::kCPU, at::kDouble).contiguous();
  const double ctr[3] = {c.data_ptr<double>()[0], c.data_ptr<double>()[1], c.data_ptr<double>()[2]};
  const Camera cam = make_camera(viewmat, K, int(width), int(height));
  std::vector<int64_t> group_rows;
  for (const auto& sp : spans) group_rows.push_back(sp.second);
  const std::vector<Segment> segs = make_segments(group_rows, seg_rows, moves, move_on, cam);
  int64_t N = 0;
  for (const int64_t n : group_rows) N += n;
  const int nt = clamp_threads(nthreads);
  if (st == at::kFloat)
    return forward_train_impl<float>(raw_groups<float>(means, quats, scales, opac, sh0, shN, spans, int(sh_degree)),
                                     N, ctr, segs, cam, near, far, eps2d, cull, st, nt);
  return forward_train_impl<double>(raw_groups<double>(means, quats, scales, opac, sh0, shN, spans, int(sh_degree)),
                                    N, ctr, segs, cam, near, far, eps2d, cull, st, nt);
}

// Returns per block of groups (``blocks`` (G,) non-decreasing block index per group; empty:
// every group its own block) [g_means, g_quats, g_log_scales, g_opacity_logits, g_sh0, g_shN]
// over the block's rows in group order, then absgrad2d (N,2), then when any segment is moved
// the sums (S,16) float64 of every segment's move gradient (see backward_train_impl).
std::vector<at::Tensor> raster_backward_train(std::vector<at::Tensor> means, std::vector<at::Tensor> quats,
                                              std::vector<at::Tensor> scales, std::vector<at::Tensor> opac,
                                              std::vector<at::Tensor> sh0, std::vector<at::Tensor> shN,
                                              at::Tensor group_spans, int64_t sh_degree, at::Tensor center,
                                              at::Tensor seg_rows, at::Tensor moves, at::Tensor move_on,
                                              at::Tensor viewmat, at::Tensor K, int64_t width, int64_t height,
                                              double near, double far, double eps2d, at::Tensor rec, at::Tensor col, at::Tensor gidx, at::Tensor offsets,
                                              at::Tensor ids, at::Tensor acc, at::Tensor dn, at::Tensor aa,
                                              at::Tensor g_acc, at::Tensor g_dn, at::Tensor g_a, at::Tensor blocks,
                                              int64_t nthreads) {
  const auto st = means[0].scalar_type();
  const auto spans = check_groups(means, quats, scales, opac, sh0, shN, group_spans, st);
  for (auto [t, n] : {std::pair{&rec, "rec"}, {&col, "colors"}, {&acc, "acc"}, {&dn, "dn"}, {&aa, "alpha"},
                      {&g_acc, "g_acc"}, {&g_dn, "g_dn"}, {&g_a, "g_alpha"}})
    check_cpu_contig(*t, st, n);
  auto c = center.detach().to(at::kCPU, at::kDouble).contiguous();
  const double ctr[3] = {c.data_ptr<double>()[0], c.data_ptr<double>()[1], c.data_ptr<double>()[2]};
  const Camera cam = make_camera(viewmat, K, int(width), int(height));
  std::vector<int64_t> group_rows;
  for (const auto& sp : spans) group_rows.push_back(sp.second);
  const std::vector<Segment> segs = make_segments(group_rows, seg_rows, moves, move_on, cam);
  std::vector<int64_t> block(means.size());
  if (blocks.numel() == 0) {
    for (size_t g = 0; g < block.size(); ++g) block[g] = int64_t(g);
  } else {
    auto b = blocks.detach().to(at::kCPU, at::kLong).contiguous();
    TORCH_CHECK(b.numel() == int64_t(block.size()), "blocks: one per group expected, got ", b.numel(), " for ",
                block.size(), " groups");
    for (size_t g = 0; g < block.size(); ++g) {
      block[g] = b.data_ptr<int64_t>()[g];
      TORCH_CHECK(g == 0 || block[g] >= block[g - 1], "blocks must be non-decreasing");
    }
  }
  int64_t N = 0;
  for (const int64_t n : group_rows) N += n;
  const int nt = clamp_threads(nthreads);
  (void)near, (void)far;  // the forward's depth range: every row with a gradient passed it
  if (st == at::kFloat)
    return backward_train_impl<float>(raw_groups<float>(means, quats, scales, opac, sh0, shN, spans, int(sh_degree)), block, N, ctr,
                                      segs, cam, eps2d, rec, col, gidx, offsets, ids, acc, dn, aa, g_acc, g_dn,
                                      g_a, st, nt);
  return backward_train_impl<double>(raw_groups<double>(means, quats, scales, opac, sh0, shN, spans, int(sh_degree)), block, N, ctr,
                                     segs, cam, eps2d, rec, col, gidx, offsets, ids, acc, dn, aa, g_acc, g_dn,
                                     g_a, st, nt);
}

// ssim.cpp
std::vector<at::Tensor> ssim_forward(at::Tensor a, at::Tensor b, at::Tensor window, int64_t nthreads);
at::Tensor ssim_backward(at::Tensor a, at::Tensor b, at::Tensor window, at::Tensor stats, at::Tensor g_map,
                         int64_t nthreads);

// The kernels touch no Python object: the GIL is released while they run, so renders of
// several cameras in threads (a rig) overlap their kernels.
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  using nogil = pybind11::call_guard<pybind11::gil_scoped_release>;
  m.def("forward", &raster_forward, "Gaussian rasterization forward (CPU)", nogil());
  m.def("backward", &raster_backward, "Gaussian rasterization backward (CPU)", nogil());
  m.def("forward_train", &raster_forward_train, "forward from raw Gaussian groups (CPU; training and inference)",
        nogil());
  m.def("backward_train", &raster_backward_train, "training backward to raw Gaussian groups (CPU)", nogil());
  m.def("ssim_forward", &ssim_forward, "SSIM map of two images (CPU)", nogil());
  m.def("ssim_backward", &ssim_backward, "gradient of the SSIM map w.r.t. the first image (CPU)", nogil());
}
