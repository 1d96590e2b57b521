// Native rollout of the sphere-packing simulator (dejaview.sim.native).
//
// The same model as dejaview/sim/contacts.py and dejaview/sim/integrate.py, written once as
// templates over the number type T: plain floats for values, and forward-mode dual numbers
// Dual<S, W> (a value and W tangents) for exact Jacobians. A substep's Jacobian is assembled from
// three small dual passes per body, whatever the number of spheres:
//
//   static contacts  W_s(s_a)          Dual<13>: d W_s / d s_a            (6 x 13)
//   body pair (a, b) W_p(s_a, s_b)     Dual<26>: d W_p / d (s_a, s_b)     (12 x 26)
//   integration      s_a' = I(s_a, W_a) Dual<19>: d s_a' / d (s_a, W_a)   (13 x 19)
//
// with s = (x, q, v, w) (13 numbers) and W = (F, tau). The rollout carries the product of the
// substep Jacobians, Phi = d s_t / d s_0 (13N x 13N), and returns it at every recorded step: a
// vector-Jacobian product (reverse mode) is then sum_t Phi_t^T g_t and a Jacobian-vector product
// (forward mode) Phi_t v, both one small contraction in torch.
//
// Contact selection (which spheres touch) is made on values, as the torch code's topk on detached
// depths; spheres that do not touch carry exactly zero force and zero derivative there, so they are
// skipped. Culling, all of it exact: a body whose centre is farther from a static shape than
// L * bound (L the shape's Lipschitz bound, bound the body's bounding radius) skips the shape; each
// sphere keeps a lower bound on its clearance to each shape, lowered every substep by L times how
// far the body moved, and is looked at only when the bound reaches zero (select_static); a body
// pair pairs only the spheres within reach of the other body's bounding sphere (select_pair).
#include <torch/extension.h>

#include <algorithm>
#include <atomic>
#include <exception>
#include <mutex>
#include <thread>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace dv {

// ------------------------------------------------------------------ dual numbers
#ifndef DV_PAD
#define DV_PAD 4
#endif
// W tangents, stored padded to a multiple of DV_PAD (zeros) so every loop is whole vectors
template <typename S, int W>
struct Dual {
  static constexpr int P = (W + DV_PAD - 1) / DV_PAD * DV_PAD;
  S d[P];
  S v;
  Dual() = default;
  Dual(S x) : v(x) {  // NOLINT: a constant
    for (int i = 0; i < P; ++i) d[i] = S(0);
  }
};

template <typename S> inline S val(S x) { return x; }
template <typename S, int W> inline S val(const Dual<S, W>& x) { return x.v; }

#define DV_D template <typename S, int W> inline Dual<S, W>
DV_D operator+(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v + b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] + b.d[i];
  return r;
}
DV_D operator-(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v - b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] - b.d[i];
  return r;
}
DV_D operator-(const Dual<S, W>& a) {
  Dual<S, W> r; r.v = -a.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = -a.d[i];
  return r;
}
DV_D operator*(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v * b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] * b.v + a.v * b.d[i];
  return r;
}
DV_D operator/(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v / b.v;
  const S inv = S(1) / b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = (a.d[i] - r.v * b.d[i]) * inv;
  return r;
}
DV_D operator+(const Dual<S, W>& a, S b) { Dual<S, W> r = a; r.v += b; return r; }
DV_D operator+(S b, const Dual<S, W>& a) { Dual<S, W> r = a; r.v += b; return r; }
DV_D operator-(const Dual<S, W>& a, S b) { Dual<S, W> r = a; r.v -= b; return r; }
DV_D operator-(S b, const Dual<S, W>& a) {
  Dual<S, W> r; r.v = b - a.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = -a.d[i];
  return r;
}
DV_D operator*(const Dual<S, W>& a, S b) {
  Dual<S, W> r; r.v = a.v * b;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] * b;
  return r;
}
DV_D operator*(S b, const Dual<S, W>& a) { return a * b; }
DV_D operator/(const Dual<S, W>& a, S b) {
  Dual<S, W> r; r.v = a.v / b;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] / b;
  return r;
}
DV_D operator/(S a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a / b.v;
  const S k = -r.v / b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = k * b.d[i];
  return r;
}
DV_D chain(const Dual<S, W>& a, S value, S slope) {
  Dual<S, W> r; r.v = value;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = slope * a.d[i];
  return r;
}
DV_D sqrt(const Dual<S, W>& a) { const S s = std::sqrt(a.v); return chain(a, s, S(0.5) / s); }
DV_D sin(const Dual<S, W>& a) { return chain(a, std::sin(a.v), std::cos(a.v)); }
DV_D cos(const Dual<S, W>& a) { return chain(a, std::cos(a.v), -std::sin(a.v)); }
DV_D sigmoid(const Dual<S, W>& a) {
  const S s = S(1) / (S(1) + std::exp(-a.v));
  return chain(a, s, s * (S(1) - s));
}
DV_D pow(const Dual<S, W>& a, S p) {
  return chain(a, std::pow(a.v, p), p * std::pow(a.v, p - S(1)));
}
DV_D abs(const Dual<S, W>& a) {
  return chain(a, std::abs(a.v), a.v > 0 ? S(1) : (a.v < 0 ? S(-1) : S(0)));
}
#undef DV_D
template <typename S> inline S sigmoid(S a) { return S(1) / (S(1) + std::exp(-a)); }
using std::abs;
using std::cos;
using std::pow;
using std::sin;
using std::sqrt;

// torch's gradient conventions at kinks: relu passes nothing at 0, clamp(min) passes at equality
template <typename T> inline T relu(const T& a) { return val(a) > 0 ? a : T(0); }
template <typename T> inline T clamp_min0(const T& a) { return val(a) >= 0 ? a : T(0); }
template <typename T> inline T clamp_max0(const T& a) { return val(a) <= 0 ? a : T(0); }
template <typename T> inline const T& vmax(const T& a, const T& b) { return val(b) > val(a) ? b : a; }
template <typename T> inline const T& vmin(const T& a, const T& b) { return val(b) < val(a) ? b : a; }

// ------------------------------------------------------------------ small vector algebra
template <typename T> inline T dot3(const T* a, const T* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
template <typename T> inline void cross3(const T* a, const T* b, T* r) {
  T r0 = a[1] * b[2] - a[2] * b[1];
  T r1 = a[2] * b[0] - a[0] * b[2];
  T r2 = a[0] * b[1] - a[1] * b[0];
  r[0] = r0; r[1] = r1; r[2] = r2;
}
// r = M v, M row-major 3 x 3
template <typename T, typename M> inline void matvec(const M* m, const T* v, T* r) {
  for (int i = 0; i < 3; ++i) r[i] = m[3 * i] * v[0] + m[3 * i + 1] * v[1] + m[3 * i + 2] * v[2];
}
// r = M^T v
template <typename T, typename M> inline void matvec_t(const M* m, const T* v, T* r) {
  for (int i = 0; i < 3; ++i) r[i] = m[i] * v[0] + m[3 + i] * v[1] + m[6 + i] * v[2];
}
// rotation matrix of a unit quaternion (w x y z), as dejaview.sim.rotation.quat_to_matrix
template <typename T> inline void quat_to_matrix(const T* q, T* r) {
  const T &w = q[0], &x = q[1], &y = q[2], &z = q[3];
  r[0] = 1.0 - 2.0 * (y * y) - 2.0 * (z * z);
  r[1] = 2.0 * (x * y) - 2.0 * (z * w);
  r[2] = 2.0 * (x * z) + 2.0 * (y * w);
  r[3] = 2.0 * (x * y) + 2.0 * (z * w);
  r[4] = 1.0 - 2.0 * (x * x) - 2.0 * (z * z);
  r[5] = 2.0 * (y * z) - 2.0 * (x * w);
  r[6] = 2.0 * (x * z) - 2.0 * (y * w);
  r[7] = 2.0 * (y * z) + 2.0 * (x * w);
  r[8] = 1.0 - 2.0 * (x * x) - 2.0 * (y * y);
}
// R A R^T with A a constant (body-frame) symmetric matrix
template <typename T, typename S> inline void rotate_tensor(const T* r, const S* a, T* out) {
  T ra[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) ra[3 * i + j] = r[3 * i] * a[j] + r[3 * i + 1] * a[3 + j] + r[3 * i + 2] * a[6 + j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      out[3 * i + j] = ra[3 * i] * r[3 * j] + ra[3 * i + 1] * r[3 * j + 1] + ra[3 * i + 2] * r[3 * j + 2];
}

// ------------------------------------------------------------------ world
template <typename S>
struct Shape {
  int kind;  // 0 plane, 1 box, 2 sphere, 3 cylinder, 4 grid
  S rot[9], trans[3], half[3], radius, half_height, origin[3], spacing, lipschitz;
  const S* grid;
  int64_t nx, ny, nz;
};

template <typename S>
struct World {
  int n, s_max, k, p;
  std::vector<int> count;  // real spheres per body
  std::vector<S> reach;    // largest sphere-centre distance from the centre of mass, per body
  const S *mass, *inertia, *inv_inertia, *centers, *radii, *bound, *inv_i_min;
  std::vector<Shape<S>> shapes;
  const S *mu_static, *unload_static;  // (N, K)
  const int64_t* pairs;                 // (P, 2)
  const S *mu_pair, *unload_pair, *mass_pair;
  S gravity[3];
  S h, omega, unload_velocity;
  int substeps, cap_static, cap_pair;
};

// signed distance and outward normal of a world point, as StaticShape.distance (values, or a
// dual number of any width through distance() below)
template <typename T, typename S>
void distance_direct(const Shape<S>& sh, const T* pw, T& dist, T* normal) {
  T rel[3] = {pw[0] - sh.trans[0], pw[1] - sh.trans[1], pw[2] - sh.trans[2]};
  T p[3];
  for (int j = 0; j < 3; ++j) p[j] = rel[0] * sh.rot[j] + rel[1] * sh.rot[3 + j] + rel[2] * sh.rot[6 + j];
  T n[3];
  const S tiny2 = S(1e-24);
  if (sh.kind == 0) {  // plane z <= 0
    dist = p[2];
    n[0] = T(0); n[1] = T(0); n[2] = T(1);
  } else if (sh.kind == 1) {  // box
    T q[3], out[3];
    S sign[3];
    for (int c = 0; c < 3; ++c) {
      sign[c] = val(p[c]) < 0 ? S(-1) : S(1);
      q[c] = abs(p[c]) - sh.half[c];
      out[c] = clamp_min0(q[c]);
    }
    T len = sqrt(dot3(out, out) + tiny2);
    int axis = 0;
    for (int c = 1; c < 3; ++c)
      if (val(q[c]) > val(q[axis])) axis = c;
    if (val(q[axis]) > 0) {
      for (int c = 0; c < 3; ++c) n[c] = out[c] / len * sign[c];
      dist = len;
    } else {
      for (int c = 0; c < 3; ++c) n[c] = T(c == axis ? sign[c] : S(0));
      dist = clamp_max0(q[axis]);
    }
  } else if (sh.kind == 2) {  // sphere
    T len = sqrt(dot3(p, p) + tiny2);
    for (int c = 0; c < 3; ++c) n[c] = p[c] / len;
    dist = len - sh.radius;
  } else if (sh.kind == 3) {  // cylinder along z
    T rlen = sqrt(p[0] * p[0] + p[1] * p[1] + tiny2);
    T radial[3] = {p[0] / rlen, p[1] / rlen, T(0)};
    T dr = rlen - sh.radius;
    T dz = abs(p[2]) - sh.half_height;
    S zs = val(p[2]) < 0 ? S(-1) : S(1);
    bool is_out = val(dr) > 0 || val(dz) > 0;
    if (is_out) {
      T c0 = clamp_min0(dr), c1 = clamp_min0(dz);
      T clen = sqrt(c0 * c0 + c1 * c1 + tiny2);
      T d0 = c0 / clen, d1 = c1 / clen;
      n[0] = radial[0] * d0; n[1] = radial[1] * d0; n[2] = d1 * zs;
      dist = clen;
    } else {
      dist = clamp_max0(vmax(dr, dz));
      if (val(dr) > val(dz)) {
        n[0] = radial[0]; n[1] = radial[1]; n[2] = T(0);
      } else {
        n[0] = T(0); n[1] = T(0); n[2] = T(zs);
      }
    }
  } else {  // grid, trilinear
    const S size[3] = {S(sh.nx - 1), S(sh.ny - 1), S(sh.nz - 1)};
    T u_in[3], excess[3];
    int64_t i0[3];
    for (int c = 0; c < 3; ++c) {
      T u = (p[c] - sh.origin[c]) / sh.spacing;
      u_in[c] = vmin(vmax(u, T(0)), T(size[c]));
      excess[c] = (u - u_in[c]) * sh.spacing;
      S f0 = std::min(std::floor(val(u_in[c])), size[c] - 1);
      i0[c] = static_cast<int64_t>(std::max(f0, S(0)));
    }
    T f[3] = {u_in[0] - S(i0[0]), u_in[1] - S(i0[1]), u_in[2] - S(i0[2])};
    T g[3] = {T(0), T(0), T(0)};
    T d = T(0);
    const int64_t sy = sh.nz, sx = sh.ny * sh.nz;
    for (int a = 0; a < 2; ++a) {
      T wx = a ? f[0] : 1.0 - f[0];
      for (int b = 0; b < 2; ++b) {
        T wy = b ? f[1] : 1.0 - f[1];
        for (int c = 0; c < 2; ++c) {
          T wz = c ? f[2] : 1.0 - f[2];
          const S v = sh.grid[(i0[0] + a) * sx + (i0[1] + b) * sy + (i0[2] + c)];
          d = d + v * wx * wy * wz;
          g[0] = g[0] + v * S(2 * a - 1) * wy * wz;
          g[1] = g[1] + v * wx * S(2 * b - 1) * wz;
          g[2] = g[2] + v * wx * wy * S(2 * c - 1);
        }
      }
    }
    T elen = sqrt(dot3(excess, excess) + tiny2);
    if (val(elen) > S(1e-9)) {
      for (int c = 0; c < 3; ++c) n[c] = excess[c] / elen;
    } else {
      for (int c = 0; c < 3; ++c) n[c] = g[c] / sh.spacing;
    }
    dist = d + elen;
  }
  for (int i = 0; i < 3; ++i) normal[i] = n[0] * sh.rot[3 * i] + n[1] * sh.rot[3 * i + 1] + n[2] * sh.rot[3 * i + 2];
}

template <typename S>
inline void distance(const Shape<S>& sh, const S* pw, S& dist, S* normal) {
  distance_direct<S, S>(sh, pw, dist, normal);
}

// dual numbers: the field is a function of the 3 world coordinates only, so it runs on 3-wide
// duals and the 4 results are chained to the W tangents of the point (chain rule)
template <typename S, int W>
void distance(const Shape<S>& sh, const Dual<S, W>* pw, Dual<S, W>& dist, Dual<S, W>* normal) {
  using D3 = Dual<S, 3>;
  D3 p3[3], d3, n3[3];
  for (int c = 0; c < 3; ++c) {
    p3[c] = D3(pw[c].v);
    p3[c].d[c] = S(1);
  }
  distance_direct<D3, S>(sh, p3, d3, n3);
  auto chain3 = [&](const D3& x, Dual<S, W>& out) {
    out.v = x.v;
    for (int i = 0; i < Dual<S, W>::P; ++i)
      out.d[i] = x.d[0] * pw[0].d[i] + x.d[1] * pw[1].d[i] + x.d[2] * pw[2].d[i];
  };
  chain3(d3, dist);
  for (int c = 0; c < 3; ++c) chain3(n3[c], normal[c]);
}

// ------------------------------------------------------------------ contact model pieces
constexpr double SLIP_EPS = 1e-3;
constexpr double SMOOTH_MIN_POWER = 8.0;

// x^8 and x^(1/8) (SMOOTH_MIN_POWER) by squarings and square roots: the values of std::pow to
// round-off, several times cheaper
static_assert(SMOOTH_MIN_POWER == 8.0, "pow8 and root8 implement SMOOTH_MIN_POWER = 8");
template <typename S> inline S pow8(S x) { const S x2 = x * x, x4 = x2 * x2; return x4 * x4; }
template <typename S> inline S root8(S x) { return std::sqrt(std::sqrt(std::sqrt(x))); }
template <typename S, int W> inline Dual<S, W> pow8(const Dual<S, W>& a) {
  const S x = a.v, x2 = x * x, x4 = x2 * x2;
  return chain(a, x4 * x4, S(8) * x4 * x2 * x);
}
template <typename S, int W> inline Dual<S, W> root8(const Dual<S, W>& a) {
  const S r = root8(a.v);
  return chain(a, r, S(0.125) * r / a.v);
}

// per-thread scratch arrays of the wrench passes (no allocation per call); slot: which one
template <typename T> inline std::vector<T>& scratch(int slot) {
  thread_local std::vector<T> v[8];
  return v[slot];
}

// friction force (contacts.friction_force)
template <typename T, typename S>
void friction(const T* vt, const T& coulomb, const T& stick, T* out) {
  T speed = sqrt(dot3(vt, vt) + S(1e-30));
  T b = stick * speed;
  T scale = vmax(coulomb, b) + S(1e-30);
  T den = root8(pow8(coulomb / scale) + pow8(b / scale) + S(1e-30)) * scale;
  T k = coulomb * stick / den;
  for (int c = 0; c < 3; ++c) out[c] = -(k * vt[c]);
}

// rotational inverse-mass term (contacts._inverse_mass) of one arm
template <typename T, typename S>
T inverse_mass(const T* arm, const T* t, const T* inv_w, S inv_i_min) {
  T u[3], iu[3];
  cross3(arm, t, u);
  matvec(inv_w, u, iu);
  T along = dot3(u, iu);
  T rest = (1.0 - dot3(t, t)) * dot3(arm, arm);
  return along + rest * inv_i_min;
}

template <typename T>
void slip_direction(const T* vt, T* t) {
  T den = sqrt(dot3(vt, vt) + SLIP_EPS * SLIP_EPS);
  for (int c = 0; c < 3; ++c) t[c] = vt[c] / den;
}

// the 13 state numbers of a body as duals, seeded as tangents offset..offset+12
template <typename S, int W>
void seed_state(const S* s, Dual<S, W>* out, int offset) {
  for (int i = 0; i < 13; ++i) {
    out[i] = Dual<S, W>(s[i]);
    out[i].d[offset + i] = S(1);
  }
}

// world centre of a body's sphere: x + R c
template <typename T, typename R, typename S>
inline void sphere_center(const T* x, const R* rot, const S* c, T* p) {
  for (int i = 0; i < 3; ++i) p[i] = x[i] + (c[0] * rot[3 * i] + c[1] * rot[3 * i + 1] + c[2] * rot[3 * i + 2]);
}

// hysteretic spring normal force of one contact (contacts.normal_force)
template <typename T, typename S>
inline T normal_force(const T& depth, const T& weight, const T& vn, S stiff, S unload, S unload_velocity) {
  T loading = sigmoid(-vn / unload_velocity);
  return weight * stiff * depth * (unload + (1.0 - unload) * loading);
}

struct Pick {
  int shape, sphere;
  double depth;
};

// which spheres of body a touch the static shapes: per shape its cap deepest.
//
// clear (K x s_max) holds a lower bound on every sphere's clearance d - r to every shape, valid at
// the previous call; move bounds how far any sphere centre of the body moved since. A shape's
// distance field is L-Lipschitz, so the bound drops by at most L * move: a sphere whose bound stays
// above CLEAR_MARGIN cannot touch and is not looked at (the result is exactly that of a full scan).
constexpr double CLEAR_MARGIN = 1e-9;

template <typename S>
void select_static(const World<S>& w, int a, const S* s, const S* rot, std::vector<Pick>& picks, S* clear,
                   S move) {
  picks.clear();
  const int cnt = w.count[a];
  const S* x = s;
  thread_local std::vector<Pick> cand;
  for (int k = 0; k < w.k; ++k) {
    const Shape<S>& sh = w.shapes[k];
    S* cl = clear + static_cast<int64_t>(k) * w.s_max;
    S dc, nc[3];
    distance<S>(sh, x, dc, nc);
    const S far = dc - sh.lipschitz * w.bound[a];
    if (far >= 0) {  // no sphere can reach the shape: d_i - r_i >= d_c - L (|c_i| + r_i) >= far
      for (int i = 0; i < cnt; ++i) cl[i] = far;
      continue;
    }
    const S drop = sh.lipschitz * move;
    cand.clear();
    for (int i = 0; i < cnt; ++i) {
      cl[i] -= drop;
      if (cl[i] > S(CLEAR_MARGIN)) continue;
      const S* c = w.centers + (static_cast<int64_t>(a) * w.s_max + i) * 3;
      S p[3];
      sphere_center(x, rot, c, p);
      S d, n[3];
      distance<S>(sh, p, d, n);
      const S r = w.radii[a * w.s_max + i];
      cl[i] = d - r;
      const S depth = r - d;
      if (depth > 0) cand.push_back({k, i, static_cast<double>(depth)});
    }
    if (static_cast<int>(cand.size()) > w.cap_static && w.s_max > w.cap_static) {
      std::nth_element(cand.begin(), cand.begin() + w.cap_static, cand.end(),
                       [](const Pick& u, const Pick& v) { return u.depth > v.depth; });
      cand.resize(w.cap_static);
    }
    picks.insert(picks.end(), cand.begin(), cand.end());
  }
}

// force and torque on body a from its picked static contacts; st = its 13 state numbers as T
template <typename T, typename S>
void static_wrench(const World<S>& w, int a, const T* st, const std::vector<Pick>& picks, T* out) {
  for (int i = 0; i < 6; ++i) out[i] = T(0);
  // a NaN anywhere in the state makes the torch model's forces NaN (0 * NaN in every candidate
  // contact, touching or not): the same here, so a broken candidate reads as broken everywhere
  for (int i = 0; i < 13 && w.k > 0; ++i)
    if (std::isnan(val(st[i]))) {
      for (int j = 0; j < 6; ++j) out[j] = T(std::numeric_limits<S>::quiet_NaN());
      return;
    }
  const int m = static_cast<int>(picks.size());
  if (m == 0) return;
  const T* x = st;
  const T* q = st + 3;
  const T* v = st + 7;
  const T* om = st + 10;
  T rot[9], inv_w[9];
  quat_to_matrix(q, rot);
  rotate_tensor(rot, w.inv_inertia + 9 * a, inv_w);
  std::vector<T>& depth = scratch<T>(0);
  std::vector<T>& nrm = scratch<T>(1);
  std::vector<T>& arm = scratch<T>(2);
  depth.resize(m);
  nrm.resize(3 * m);
  arm.resize(3 * m);
  T total = T(0);
  for (int j = 0; j < m; ++j) {
    const Pick& pk = picks[j];
    const S* c = w.centers + (static_cast<int64_t>(a) * w.s_max + pk.sphere) * 3;
    const S r = w.radii[a * w.s_max + pk.sphere];
    T p[3];
    sphere_center(x, rot, c, p);
    T d;
    distance(w.shapes[pk.shape], p, d, &nrm[3 * j]);
    depth[j] = relu(r - d);
    for (int i = 0; i < 3; ++i) arm[3 * j + i] = (p[i] - x[i]) - nrm[3 * j + i] * r;
    total = total + depth[j];
  }
  const S tiny = std::numeric_limits<S>::min();
  const S mass = w.mass[a];
  const S stiff = mass * w.omega * w.omega;
  const S inv_m = S(1) / mass;
  for (int j = 0; j < m; ++j) {
    const int k = picks[j].shape;
    const T* n = &nrm[3 * j];
    const T* r = &arm[3 * j];
    T wr[3], vel[3], vt[3], t[3], ft[3];
    cross3(om, r, wr);
    for (int i = 0; i < 3; ++i) vel[i] = v[i] + wr[i];
    T vn = dot3(vel, n);
    for (int i = 0; i < 3; ++i) vt[i] = vel[i] - vn * n[i];
    T weight = depth[j] / (total + tiny);
    T fn = normal_force(depth[j], weight, vn, stiff, w.unload_static[a * w.k + k], w.unload_velocity);
    slip_direction(vt, t);
    T inv_mass = inv_m + inverse_mass(r, t, inv_w, w.inv_i_min[a]);
    T stick = weight / (inv_mass * w.h);
    friction<T, S>(vt, w.mu_static[a * w.k + k] * fn, stick, ft);
    T f[3], tq[3];
    for (int i = 0; i < 3; ++i) f[i] = fn * n[i] + ft[i];
    cross3(r, f, tq);
    for (int i = 0; i < 3; ++i) {
      out[i] = out[i] + f[i];
      out[3 + i] = out[3 + i] + tq[i];
    }
  }
}

// per-thread scratch of select_pair (no allocation per call)
template <typename S> std::vector<int>& pair_ids_a() { thread_local std::vector<int> v; return v; }
template <typename S> std::vector<int>& pair_ids_b() { thread_local std::vector<int> v; return v; }
template <typename S> std::vector<S>& pair_pts_a() { thread_local std::vector<S> v; return v; }
template <typename S> std::vector<S>& pair_pts_b() { thread_local std::vector<S> v; return v; }

struct PairPick {
  int i, j;
  double depth;
};

// Returns a lower bound on the clearance |p_i - p_j| - r_i - r_j of every sphere pair (exact
// distances for the pairs looked at, the mid phase's margin for the others).
template <typename S>
S select_pair(const World<S>& w, int a, int b, const S* sa, const S* sb, const S* ra, const S* rb,
              std::vector<PairPick>& picks) {
  picks.clear();
  S dx[3] = {sa[0] - sb[0], sa[1] - sb[1], sa[2] - sb[2]};
  const S centres = std::sqrt(dot3(dx, dx));
  if (!(centres < w.bound[a] + w.bound[b])) return centres - (w.bound[a] + w.bound[b]);
  // mid phase: sphere i of a can touch some sphere j of b only if |p_i - x_b| < r_i + bound_b
  // (|p_i - p_j| < r_i + r_j and |p_j - x_b| + r_j <= bound_b); likewise for b's spheres. A
  // sphere left out is at least |p_i - x_b| - r_i - bound_b >= 0 clear of every sphere of b.
  S bound = std::numeric_limits<S>::infinity();
  auto near = [&](int body, const S* st, const S* rot, const S* other, S other_bound,
                  std::vector<int>& ids, std::vector<S>& pts) {
    ids.clear();
    pts.clear();
    for (int i = 0; i < w.count[body]; ++i) {
      const S* c = w.centers + (static_cast<int64_t>(body) * w.s_max + i) * 3;
      S p[3], d[3];
      sphere_center(st, rot, c, p);
      for (int k = 0; k < 3; ++k) d[k] = p[k] - other[k];
      const S gap = std::sqrt(dot3(d, d)) - (w.radii[body * w.s_max + i] + other_bound);
      if (gap < 0) {
        ids.push_back(i);
        pts.insert(pts.end(), p, p + 3);
      } else {
        bound = std::min(bound, gap);
      }
    }
  };
  std::vector<int>& ia = pair_ids_a<S>();
  std::vector<int>& ib = pair_ids_b<S>();
  std::vector<S>& pa = pair_pts_a<S>();
  std::vector<S>& pb = pair_pts_b<S>();
  near(a, sa, ra, sb, w.bound[b], ia, pa);
  if (ia.empty()) return bound;
  near(b, sb, rb, sa, w.bound[a], ib, pb);
  for (size_t u = 0; u < ia.size(); ++u) {
    const S r_i = w.radii[a * w.s_max + ia[u]];
    for (size_t v = 0; v < ib.size(); ++v) {
      S df[3] = {pb[3 * v] - pa[3 * u], pb[3 * v + 1] - pa[3 * u + 1], pb[3 * v + 2] - pa[3 * u + 2]};
      const S depth = r_i + w.radii[b * w.s_max + ib[v]] - std::sqrt(dot3(df, df));
      if (depth > 0) picks.push_back({ia[u], ib[v], static_cast<double>(depth)});
      bound = std::min(bound, -depth);
    }
  }
  if (static_cast<int>(picks.size()) > w.cap_pair &&
      static_cast<int64_t>(w.s_max) * w.s_max > w.cap_pair) {
    std::nth_element(picks.begin(), picks.begin() + w.cap_pair, picks.end(),
                     [](const PairPick& u, const PairPick& v) { return u.depth > v.depth; });
    picks.resize(w.cap_pair);
  }
  return bound;
}

// wrench on a (out[0..5]) and on b (out[6..11]) from pair index pi's picked sphere pairs
template <typename T, typename S>
void pair_wrench(const World<S>& w, int pi, const T* st_a, const T* st_b, const std::vector<PairPick>& picks,
                 T* out) {
  for (int i = 0; i < 12; ++i) out[i] = T(0);
  const int m = static_cast<int>(picks.size());
  if (m == 0) return;
  const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
  T rot_a[9], rot_b[9], iw_a[9], iw_b[9];
  quat_to_matrix(st_a + 3, rot_a);
  quat_to_matrix(st_b + 3, rot_b);
  rotate_tensor(rot_a, w.inv_inertia + 9 * a, iw_a);
  rotate_tensor(rot_b, w.inv_inertia + 9 * b, iw_b);
  std::vector<T>& depth = scratch<T>(3);
  std::vector<T>& nrm = scratch<T>(4);
  std::vector<T>& arm_a = scratch<T>(5);
  std::vector<T>& arm_b = scratch<T>(6);
  depth.resize(m);
  nrm.resize(3 * m);
  arm_a.resize(3 * m);
  arm_b.resize(3 * m);
  T total = T(0);
  for (int k = 0; k < m; ++k) {
    const S* ca = w.centers + (static_cast<int64_t>(a) * w.s_max + picks[k].i) * 3;
    const S* cb = w.centers + (static_cast<int64_t>(b) * w.s_max + picks[k].j) * 3;
    const S r_a = w.radii[a * w.s_max + picks[k].i], r_b = w.radii[b * w.s_max + picks[k].j];
    T pa[3], pb[3], diff[3];
    sphere_center(st_a, rot_a, ca, pa);
    sphere_center(st_b, rot_b, cb, pb);
    for (int i = 0; i < 3; ++i) diff[i] = pb[i] - pa[i];
    T dist = sqrt(dot3(diff, diff) + S(1e-24));
    for (int i = 0; i < 3; ++i) nrm[3 * k + i] = diff[i] / dist;
    depth[k] = relu((r_a + r_b) - dist);
    for (int i = 0; i < 3; ++i) {
      T point = pa[i] + nrm[3 * k + i] * r_a;
      arm_a[3 * k + i] = point - st_a[i];
      arm_b[3 * k + i] = point - st_b[i];
    }
    total = total + depth[k];
  }
  const S tiny = std::numeric_limits<S>::min();
  const S stiff = w.mass_pair[pi] * w.omega * w.omega;
  const S unload = w.unload_pair[pi];
  const S inv_m = S(1) / w.mass[a] + S(1) / w.mass[b];
  for (int k = 0; k < m; ++k) {
    const T* n = &nrm[3 * k];
    const T* ra = &arm_a[3 * k];
    const T* rb = &arm_b[3 * k];
    T wa[3], wb[3], vrel[3], vt[3], t[3], ft[3];
    cross3(st_a + 10, ra, wa);
    cross3(st_b + 10, rb, wb);
    for (int i = 0; i < 3; ++i) vrel[i] = (st_b[7 + i] + wb[i]) - (st_a[7 + i] + wa[i]);
    T vn = dot3(vrel, n);
    for (int i = 0; i < 3; ++i) vt[i] = vrel[i] - vn * n[i];
    T weight = depth[k] / (total + tiny);
    T fn = normal_force(depth[k], weight, vn, stiff, unload, w.unload_velocity);
    slip_direction(vt, t);
    T inv_mass = inv_m + inverse_mass(ra, t, iw_a, w.inv_i_min[a]) + inverse_mass(rb, t, iw_b, w.inv_i_min[b]);
    T stick = weight / (inv_mass * w.h);
    friction<T, S>(vt, w.mu_pair[pi] * fn, stick, ft);
    T f[3], neg[3], ta[3], tb[3];
    for (int i = 0; i < 3; ++i) {
      f[i] = fn * n[i] + ft[i];
      neg[i] = -f[i];
    }
    cross3(ra, neg, ta);
    cross3(rb, f, tb);
    for (int i = 0; i < 3; ++i) {
      out[i] = out[i] - f[i];
      out[3 + i] = out[3 + i] + ta[i];
      out[6 + i] = out[6 + i] + f[i];
      out[9 + i] = out[9 + i] + tb[i];
    }
  }
}

// one semi-implicit Euler substep of one body from its state st (13) and wrench wr (6, gravity included)
template <typename T, typename S>
void integrate(const World<S>& w, int a, const T* st, const T* wr, T* out) {
  const T* q = st + 3;
  T rot[9];
  quat_to_matrix(q, rot);
  const S hm = w.h / w.mass[a];
  T v[3], om[3], lw[3], gyro[3], rhs[3], acc[3], body[3], tmp[3];
  for (int i = 0; i < 3; ++i) v[i] = st[7 + i] + hm * wr[i];
  // I_w w and I_w^-1 (tau - gyro) as R (I (R^T u)): matrix-vector products only
  matvec_t(rot, st + 10, body);
  matvec(w.inertia + 9 * a, body, tmp);
  matvec(rot, tmp, lw);
  cross3(st + 10, lw, gyro);
  for (int i = 0; i < 3; ++i) rhs[i] = wr[3 + i] - gyro[i];
  matvec_t(rot, rhs, body);
  matvec(w.inv_inertia + 9 * a, body, tmp);
  matvec(rot, tmp, acc);
  for (int i = 0; i < 3; ++i) om[i] = st[10 + i] + w.h * acc[i];
  for (int i = 0; i < 3; ++i) out[i] = st[i] + w.h * v[i];
  // rotvec_to_quat(om h) * q, renormalised
  T r[3] = {om[0] * w.h, om[1] * w.h, om[2] * w.h};
  const S eps = sizeof(S) == 8 ? S(1e-4) : S(1e-2);
  T sq = dot3(r, r);
  T sinc, co;
  if (val(sq) < eps * eps) {
    sinc = 0.5 - sq / S(48);
    co = 1.0 - sq / S(8);
  } else {
    T norm = sqrt(sq);
    T half = 0.5 * norm;
    sinc = sin(half) / norm;
    co = cos(half);
  }
  T e[4] = {co, sinc * r[0], sinc * r[1], sinc * r[2]};
  T qn[4];
  qn[0] = e[0] * q[0] - e[1] * q[1] - e[2] * q[2] - e[3] * q[3];
  qn[1] = e[0] * q[1] + e[1] * q[0] + e[2] * q[3] - e[3] * q[2];
  qn[2] = e[0] * q[2] - e[1] * q[3] + e[2] * q[0] + e[3] * q[1];
  qn[3] = e[0] * q[3] + e[1] * q[2] - e[2] * q[1] + e[3] * q[0];
  T len = sqrt(qn[0] * qn[0] + qn[1] * qn[1] + qn[2] * qn[2] + qn[3] * qn[3]);
  for (int i = 0; i < 4; ++i) out[3 + i] = qn[i] / len;
  for (int i = 0; i < 3; ++i) {
    out[7 + i] = v[i];
    out[10 + i] = om[i];
  }
}

// ------------------------------------------------------------------ one candidate
template <typename S>
struct Scratch {
  std::vector<std::vector<Pick>> picks;          // per body
  std::vector<std::vector<PairPick>> pair_picks;  // per pair
  std::vector<S> rot;                             // (N, 9)
  std::vector<S> wrench;                          // (N, 6)
  std::vector<S> next;                            // (N, 13)
  std::vector<S> jac, dws;                        // substep Jacobian (13N)^2, dW/ds (6N x 13N)
  std::vector<S> clear;                           // (N, K, s_max) clearance bounds (select_static)
  std::vector<S> last;                            // (N, 12) position and rotation at the last selection
  std::vector<char> blk;                          // (N, N) nonzero 13 x 13 blocks of the Jacobian
  std::vector<S> pair_jac;                        // (P, 12, 26) pair blocks (substep_adjoint)
  std::vector<S> move;                            // (N) how far a sphere of each body moved this substep
  std::vector<S> static_move;                     // (N) ... since its last select_static
  std::vector<S> pair_clear;                      // (P) clearance bound of each pair (select_pair)
};

// which spheres touch at state (contact selection on values, the clearance bounds of sc updated)
// which spheres touch at state (contact selection on values, the clearance bounds of sc updated).
// need (N, or null for all): bodies whose contacts are wanted; the others get no static picks,
// and a pair of two such bodies none (reverse mode skips bodies its adjoint has not reached).
//
// Pairs keep a lower bound on the clearance |p_i - p_j| - r_i - r_j of every sphere pair, set
// by select_pair and lowered every substep by how far either body moved: a pair whose bound
// stays above CLEAR_MARGIN cannot touch and is skipped (exact, as select_static's bounds).
template <typename S>
void select_contacts(const World<S>& w, const S* state, Scratch<S>& sc, const char* need = nullptr) {
  const int n = w.n;
  for (int a = 0; a < n; ++a) {
    S* rot = &sc.rot[9 * a];
    S* last = &sc.last[12 * a];
    quat_to_matrix(state + 13 * a + 3, rot);
    S dx = 0, dr = 0;
    for (int i = 0; i < 3; ++i) dx += (state[13 * a + i] - last[i]) * (state[13 * a + i] - last[i]);
    for (int i = 0; i < 9; ++i) dr += (rot[i] - last[3 + i]) * (rot[i] - last[3 + i]);
    // |p_i' - p_i| <= |x' - x| + |R' - R|_F |c_i|
    const S move = std::sqrt(dx) + std::sqrt(dr) * w.reach[a];
    for (int i = 0; i < 3; ++i) last[i] = state[13 * a + i];
    for (int i = 0; i < 9; ++i) last[3 + i] = rot[i];
    sc.move[a] = move;
    sc.static_move[a] += move;  // since this body's last select_static
    if (need != nullptr && !need[a]) {
      sc.picks[a].clear();
      continue;
    }
    select_static(w, a, state + 13 * a, rot, sc.picks[a],
                  &sc.clear[static_cast<int64_t>(a) * w.k * w.s_max], sc.static_move[a]);
    sc.static_move[a] = S(0);
  }
  for (int pi = 0; pi < w.p; ++pi) {
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    S& bound = sc.pair_clear[pi];
    bound -= sc.move[a] + sc.move[b];
    if (bound > S(CLEAR_MARGIN) || (need != nullptr && !need[a] && !need[b])) {
      sc.pair_picks[pi].clear();
      continue;
    }
    bound = select_pair(w, a, b, state + 13 * a, state + 13 * b, &sc.rot[9 * a], &sc.rot[9 * b],
                        sc.pair_picks[pi]);
  }
}

template <typename S>
void substep(const World<S>& w, S* state, Scratch<S>& sc, S* jac /* (13N)^2 or null */) {
  const int n = w.n;
  const int dim = 13 * n;
  select_contacts(w, state, sc);
  if (jac == nullptr) {
    for (int a = 0; a < n; ++a) static_wrench<S, S>(w, a, state + 13 * a, sc.picks[a], &sc.wrench[6 * a]);
    for (int pi = 0; pi < w.p; ++pi) {
      if (sc.pair_picks[pi].empty()) continue;
      const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
      S o[12];
      pair_wrench<S, S>(w, pi, state + 13 * a, state + 13 * b, sc.pair_picks[pi], o);
      for (int i = 0; i < 6; ++i) {
        sc.wrench[6 * a + i] += o[i];
        sc.wrench[6 * b + i] += o[6 + i];
      }
    }
    for (int a = 0; a < n; ++a) {
      for (int i = 0; i < 3; ++i) sc.wrench[6 * a + i] += w.mass[a] * w.gravity[i];
      integrate<S, S>(w, a, state + 13 * a, &sc.wrench[6 * a], &sc.next[13 * a]);
    }
    std::copy(sc.next.begin(), sc.next.end(), state);
    return;
  }
  // Jacobian: dW/ds per body (6 x 13N), then integration
  std::fill(sc.dws.begin(), sc.dws.end(), S(0));  // (N, 6, 13N)
  sc.blk.assign(static_cast<size_t>(n) * n, 0);
  for (int a = 0; a < n; ++a) sc.blk[a * n + a] = 1;
  for (int a = 0; a < n; ++a) {
    using D = Dual<S, 13>;
    D st[13], o[6];
    seed_state(state + 13 * a, st, 0);
    static_wrench<D, S>(w, a, st, sc.picks[a], o);
    for (int i = 0; i < 6; ++i) {
      sc.wrench[6 * a + i] = o[i].v;
      for (int j = 0; j < 13; ++j) sc.dws[(static_cast<int64_t>(6 * a + i)) * dim + 13 * a + j] = o[i].d[j];
    }
  }
  for (int pi = 0; pi < w.p; ++pi) {
    if (sc.pair_picks[pi].empty()) continue;
    using D = Dual<S, 26>;
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    D sa[13], sb[13], o[12];
    seed_state(state + 13 * a, sa, 0);
    seed_state(state + 13 * b, sb, 13);
    pair_wrench<D, S>(w, pi, sa, sb, sc.pair_picks[pi], o);
    sc.blk[a * n + b] = sc.blk[b * n + a] = 1;
    for (int half = 0; half < 2; ++half) {
      const int body = half ? b : a;
      for (int i = 0; i < 6; ++i) {
        const D& f = o[6 * half + i];
        sc.wrench[6 * body + i] += f.v;
        S* row = &sc.dws[static_cast<int64_t>(6 * body + i) * dim];
        for (int j = 0; j < 13; ++j) {
          row[13 * a + j] += f.d[j];
          row[13 * b + j] += f.d[13 + j];
        }
      }
    }
  }
  std::fill(sc.jac.begin(), sc.jac.end(), S(0));
  for (int a = 0; a < n; ++a) {
    using D = Dual<S, 19>;
    D st[13], wr[6], o[13];
    seed_state(state + 13 * a, st, 0);
    for (int i = 0; i < 6; ++i) {
      S value = sc.wrench[6 * a + i] + (i < 3 ? w.mass[a] * w.gravity[i] : S(0));
      wr[i] = D(value);
      wr[i].d[13 + i] = S(1);
    }
    integrate<D, S>(w, a, st, wr, o);
    for (int i = 0; i < 13; ++i) {
      sc.next[13 * a + i] = o[i].v;
      S* row = jac + static_cast<int64_t>(13 * a + i) * dim;
      for (int j = 0; j < 13; ++j) row[13 * a + j] += o[i].d[j];
      for (int k = 0; k < 6; ++k) {
        const S g = o[i].d[13 + k];
        if (g == S(0)) continue;
        const S* dw = &sc.dws[static_cast<int64_t>(6 * a + k) * dim];
        for (int j = 0; j < dim; ++j) row[j] += g * dw[j];
      }
    }
  }
  std::copy(sc.next.begin(), sc.next.end(), state);
}

// Reverse mode, one substep: lam <- J(state)^T lam, J = d state' / d state the substep's Jacobian,
// from the same dual passes as substep(..., jac) but without assembling J: with
// s_a' = I(s_a, W_a) and W_a = W_s(s_a) + sum over touching pairs W_p(s_a, s_b),
//   mu_a = (dI/dW_a)^T lam_a,  lam_a <- (dI/ds_a)^T lam_a + (dW_s/ds_a)^T mu_a + pair terms.
// A body whose adjoint lam_a is zero has mu_a = 0: its integration and static contacts are then
// skipped, and a pair only when both of its bodies are (bodies no contact chain connects to the
// loss cost a value pass of their pairs at most).
template <typename S>
void substep_adjoint(const World<S>& w, const S* state, Scratch<S>& sc, S* lam) {
  const int n = w.n;
  std::vector<char>& live = sc.blk;  // per body: adjoint nonzero
  live.assign(n, 0);
  for (int a = 0; a < n; ++a)
    for (int i = 0; i < 13; ++i)
      if (lam[13 * a + i] != S(0)) { live[a] = 1; break; }
  select_contacts(w, state, sc, live.data());
  // wrench values of every live body (pairs: duals where a live body takes part)
  std::fill(sc.wrench.begin(), sc.wrench.end(), S(0));
  sc.next.assign(13 * n, S(0));  // the new adjoint
  std::vector<S>& mu = sc.dws;   // (N, 6)
  mu.assign(6 * n, S(0));
  std::vector<S>& dstatic = sc.jac;  // (N, 6, 13) static contacts' d W_s / d s_a
  dstatic.resize(static_cast<size_t>(78) * n);
  for (int a = 0; a < n; ++a) {
    if (!live[a]) continue;
    using D = Dual<S, 13>;
    D st[13], o[6];
    seed_state(state + 13 * a, st, 0);
    static_wrench<D, S>(w, a, st, sc.picks[a], o);
    for (int i = 0; i < 6; ++i) {
      sc.wrench[6 * a + i] = o[i].v;
      for (int j = 0; j < 13; ++j) dstatic[78 * a + 13 * i + j] = o[i].d[j];
    }
  }
  std::vector<S>& dpair = sc.pair_jac;  // per touching pair with a live body: (12, 26)
  dpair.resize(static_cast<size_t>(312) * w.p);
  for (int pi = 0; pi < w.p; ++pi) {
    if (sc.pair_picks[pi].empty()) continue;
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    if (!live[a] && !live[b]) continue;
    using D = Dual<S, 26>;
    D sa[13], sb[13], o[12];
    seed_state(state + 13 * a, sa, 0);
    seed_state(state + 13 * b, sb, 13);
    pair_wrench<D, S>(w, pi, sa, sb, sc.pair_picks[pi], o);
    for (int i = 0; i < 6; ++i) {
      sc.wrench[6 * a + i] += o[i].v;
      sc.wrench[6 * b + i] += o[6 + i].v;
    }
    S* blk = &dpair[312 * static_cast<size_t>(pi)];
    for (int i = 0; i < 12; ++i)
      for (int j = 0; j < 26; ++j) blk[26 * i + j] = o[i].d[j];
  }
  // integration of each live body: its own adjoint and mu
  for (int a = 0; a < n; ++a) {
    if (!live[a]) continue;
    using D = Dual<S, 19>;
    D st[13], wr[6], o[13];
    seed_state(state + 13 * a, st, 0);
    for (int i = 0; i < 6; ++i) {
      S value = sc.wrench[6 * a + i] + (i < 3 ? w.mass[a] * w.gravity[i] : S(0));
      wr[i] = D(value);
      wr[i].d[13 + i] = S(1);
    }
    integrate<D, S>(w, a, st, wr, o);
    const S* la = lam + 13 * a;
    S* na = &sc.next[13 * a];
    for (int i = 0; i < 13; ++i) {
      const S l = la[i];
      if (l == S(0)) continue;
      for (int j = 0; j < 13; ++j) na[j] += l * o[i].d[j];
      for (int k = 0; k < 6; ++k) mu[6 * a + k] += l * o[i].d[13 + k];
    }
    const S* ds = &dstatic[78 * a];
    for (int k = 0; k < 6; ++k) {
      const S m = mu[6 * a + k];
      if (m == S(0)) continue;
      for (int j = 0; j < 13; ++j) na[j] += m * ds[13 * k + j];
    }
  }
  for (int pi = 0; pi < w.p; ++pi) {
    if (sc.pair_picks[pi].empty()) continue;
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    if (!live[a] && !live[b]) continue;
    const S* blk = &dpair[312 * static_cast<size_t>(pi)];
    S* na = &sc.next[13 * a];
    S* nb = &sc.next[13 * b];
    for (int half = 0; half < 2; ++half) {
      const S* m = &mu[6 * (half ? b : a)];
      for (int k = 0; k < 6; ++k) {
        if (m[k] == S(0)) continue;
        const S* row = blk + 26 * (6 * half + k);
        for (int j = 0; j < 13; ++j) {
          na[j] += m[k] * row[j];
          nb[j] += m[k] * row[13 + j];
        }
      }
    }
  }
  std::copy(sc.next.begin(), sc.next.end(), lam);
}

// out = J phi, all dim x dim row-major; fixed sizes for 1 to 4 bodies so the loops unroll
template <typename S, int D>
void phi_update_fixed(const S* __restrict J, const S* __restrict phi, S* __restrict out) {
  for (int i = 0; i < D; ++i) {
    S acc[D] = {};
    for (int l = 0; l < D; ++l) {
      const S jil = J[i * D + l];
      for (int j = 0; j < D; ++j) acc[j] += jil * phi[l * D + j];
    }
    for (int j = 0; j < D; ++j) out[i * D + j] = acc[j];
  }
}

// several bodies: J is block-sparse (13 x 13 blocks; body a's rows reach body b's columns only
// through a touching pair), so only the blocks marked in blk (N x N) are multiplied
template <typename S>
void phi_update(int dim, const S* J, const S* phi, S* out, const std::vector<char>& blk) {
  if (dim == 13) return phi_update_fixed<S, 13>(J, phi, out);
  const int n = dim / 13;
  std::fill(out, out + static_cast<size_t>(dim) * dim, S(0));
  for (int a = 0; a < n; ++a)
    for (int b = 0; b < n; ++b) {
      if (!blk[a * n + b]) continue;
      for (int i = 0; i < 13; ++i) {
        S* o = out + static_cast<size_t>(13 * a + i) * dim;
        const S* jrow = J + static_cast<size_t>(13 * a + i) * dim + 13 * b;
        for (int l = 0; l < 13; ++l) {
          const S jil = jrow[l];
          const S* prow = phi + static_cast<size_t>(13 * b + l) * dim;
          for (int j = 0; j < dim; ++j) o[j] += jil * prow[j];
        }
      }
    }
}

// Divergence check of forward simulations (dejaview.sim.divergence): the first quantity of body
// state s (13 numbers) that is not finite or out of range -- 0 position (|coordinate| > reach),
// 1 orientation, 2 linear velocity (|v| > speed), 3 angular velocity (|w| bound > speed) -- or -1.
template <typename S>
inline int diverged(const S* s, S reach, S speed, S bound) {
  for (int i = 0; i < 3; ++i)
    if (!(std::abs(s[i]) <= reach)) return 0;  // NaN fails every comparison
  for (int i = 3; i < 7; ++i)
    if (!std::isfinite(s[i])) return 1;
  const S v2 = s[7] * s[7] + s[8] * s[8] + s[9] * s[9];
  if (!(v2 <= speed * speed)) return 2;
  const S w2 = s[10] * s[10] + s[11] * s[11] + s[12] * s[12];
  if (!(w2 * bound * bound <= speed * speed)) return 3;
  return -1;
}

// limits: nullptr, or {reach, speed}: a body whose state diverges (above) ends the candidate; its
// state is then the last record written, status = {step, body, quantity, record} and the records
// after it are NaN. status stays {-1, -1, -1, -1} otherwise.
template <typename S>
void init_scratch(const World<S>& w, Scratch<S>& sc) {
  const int n = w.n;
  sc.picks.resize(n);
  sc.pair_picks.resize(w.p);
  sc.rot.resize(9 * n);
  sc.wrench.resize(6 * n);
  sc.next.resize(13 * n);
  sc.clear.assign(static_cast<size_t>(n) * w.k * w.s_max, -std::numeric_limits<S>::infinity());
  sc.last.assign(static_cast<size_t>(12) * n, std::numeric_limits<S>::infinity());
  sc.move.assign(n, S(0));
  sc.static_move.assign(n, S(0));
  sc.pair_clear.assign(w.p, -std::numeric_limits<S>::infinity());
}

// Substep states kept for reverse mode (trace): per step the states before substeps k0..substeps-1,
// k0 = 1 when every step is recorded (the state before substep 0 is then the previous record, or
// init), else 0.
inline int trace_first(int64_t record_every) { return record_every == 1 ? 1 : 0; }

template <typename S>
void run_candidate(const World<S>& w, const S* init, int64_t steps, int64_t record_every, bool with_jac,
                   S* rec_states, S* rec_phi, const S* limits, int64_t* status, S* trace = nullptr) {
  const int n = w.n;
  const int dim = 13 * n;
  Scratch<S> sc;
  init_scratch(w, sc);
  const int k0 = trace_first(record_every);
  std::vector<S> state(init, init + dim);
  std::vector<S> phi, tmp;
  if (with_jac) {
    phi.assign(static_cast<size_t>(dim) * dim, S(0));
    for (int i = 0; i < dim; ++i) phi[static_cast<size_t>(i) * dim + i] = S(1);
    tmp.resize(static_cast<size_t>(dim) * dim);
    sc.jac.resize(static_cast<size_t>(dim) * dim);
    sc.dws.resize(static_cast<size_t>(6 * n) * dim);
  }
  int64_t r = 0;
  for (int64_t step = 1; step <= steps; ++step) {
    for (int k = 0; k < w.substeps; ++k) {
      if (trace != nullptr && k >= k0) {
        std::copy(state.begin(), state.end(), trace);
        trace += dim;
      }
      if (!with_jac) {
        substep<S>(w, state.data(), sc, nullptr);
        continue;
      }
      substep(w, state.data(), sc, sc.jac.data());
      phi_update<S>(dim, sc.jac.data(), phi.data(), tmp.data(), sc.blk);  // phi <- J phi
      phi.swap(tmp);
    }
    int bad_body = -1, bad_quantity = -1;
    if (limits) {
      for (int a = 0; a < n && bad_body < 0; ++a) {
        bad_quantity = diverged<S>(state.data() + 13 * a, limits[0], limits[1], w.bound[a]);
        if (bad_quantity >= 0) bad_body = a;
      }
    }
    if (bad_body >= 0 || step % record_every == 0 || step == steps) {
      std::copy(state.begin(), state.end(), rec_states + r * dim);
      if (with_jac) std::copy(phi.begin(), phi.end(), rec_phi + r * static_cast<int64_t>(dim) * dim);
      ++r;
    }
    if (bad_body >= 0) {
      status[0] = step; status[1] = bad_body; status[2] = bad_quantity; status[3] = r - 1;
      const int64_t records = (steps + record_every - 1) / record_every;
      const S nan = std::numeric_limits<S>::quiet_NaN();
      std::fill(rec_states + r * dim, rec_states + records * dim, nan);
      if (with_jac)
        std::fill(rec_phi + r * static_cast<int64_t>(dim) * dim, rec_phi + records * static_cast<int64_t>(dim) * dim, nan);
      return;
    }
  }
}

// Reverse mode of one candidate from its rollout (init, records, trace of run_candidate):
// grad_init = sum_t Phi_t^T grad_t, as lam <- J^T lam backwards through the substeps.
template <typename S>
void adjoint_candidate(const World<S>& w, const S* init, int64_t steps, int64_t record_every,
                       const S* rec_states, const S* trace, const S* grad, S* out) {
  const int n = w.n;
  const int dim = 13 * n;
  Scratch<S> sc;
  init_scratch(w, sc);
  const int k0 = trace_first(record_every);
  const int per_step = w.substeps - k0;
  std::vector<S> lam(dim, S(0));
  int64_t r = (steps + record_every - 1) / record_every - 1;
  for (int64_t step = steps; step >= 1; --step) {
    if (step % record_every == 0 || step == steps) {
      const S* g = grad + r * dim;
      for (int i = 0; i < dim; ++i) lam[i] += g[i];
      --r;
    }
    for (int k = w.substeps - 1; k >= 0; --k) {
      const S* s;
      if (k >= k0) s = trace + ((step - 1) * per_step + (k - k0)) * static_cast<int64_t>(dim);
      else s = step == 1 ? init : rec_states + (step - 2) * static_cast<int64_t>(dim);  // record_every 1
      substep_adjoint(w, s, sc, lam.data());
    }
  }
  std::copy(lam.begin(), lam.end(), out);
}

// candidates 0..b-1 spread over threads, handed out one at a time (they differ in cost: contacts)
template <typename F>
void parallel_for(int64_t b, int64_t threads, F work) {
  const int64_t workers = std::min<int64_t>(std::max<int64_t>(threads, 1), b);
  if (workers <= 1) {
    for (int64_t i = 0; i < b; ++i) work(i);
    return;
  }
  std::atomic<int64_t> next{0};
  std::vector<std::thread> pool;
  std::exception_ptr error;
  std::mutex error_lock;
  for (int64_t t = 0; t < workers; ++t)
    pool.emplace_back([&] {
      try {
        for (int64_t i = next++; i < b; i = next++) work(i);
      } catch (...) {
        std::lock_guard<std::mutex> guard(error_lock);
        error = std::current_exception();
      }
    });
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
}

template <typename S>
World<S> make_world(const std::vector<torch::Tensor>& t, const std::vector<double>& f, const std::vector<int64_t>& iv) {
  // t: mass, inertia, inv_inertia, centers, radii, bound, inv_i_min, counts(int64), mu_static, unload_static,
  //    pairs(int64), mu_pair, unload_pair, mass_pair, shape_params (K, 32), grid values (flat)
  // f: gravity(3), h, omega, unload_velocity; iv: substeps, cap_static, cap_pair, grid offsets/dims in shape_params
  World<S> w;
  w.n = static_cast<int>(t[0].size(0));
  w.s_max = static_cast<int>(t[3].size(1));
  w.k = static_cast<int>(t[8].size(1));
  w.p = static_cast<int>(t[10].size(0));
  w.mass = t[0].data_ptr<S>();
  w.inertia = t[1].data_ptr<S>();
  w.inv_inertia = t[2].data_ptr<S>();
  w.centers = t[3].data_ptr<S>();
  w.radii = t[4].data_ptr<S>();
  w.bound = t[5].data_ptr<S>();
  w.inv_i_min = t[6].data_ptr<S>();
  const int64_t* counts = t[7].data_ptr<int64_t>();
  for (int i = 0; i < w.n; ++i) {
    w.count.push_back(static_cast<int>(counts[i]));
    S reach = 0;
    for (int j = 0; j < w.count[i]; ++j) {
      const S* c = w.centers + (static_cast<int64_t>(i) * w.s_max + j) * 3;
      reach = std::max(reach, std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]));
    }
    w.reach.push_back(reach);
  }
  w.mu_static = t[8].data_ptr<S>();
  w.unload_static = t[9].data_ptr<S>();
  w.pairs = t[10].data_ptr<int64_t>();
  w.mu_pair = t[11].data_ptr<S>();
  w.unload_pair = t[12].data_ptr<S>();
  w.mass_pair = t[13].data_ptr<S>();
  const S* sp = t[14].data_ptr<S>();  // (K, 32)
  const S* grid = t[15].data_ptr<S>();
  for (int k = 0; k < w.k; ++k) {
    const S* r = sp + 32 * k;
    Shape<S> sh;
    sh.kind = static_cast<int>(r[0]);
    for (int i = 0; i < 9; ++i) sh.rot[i] = r[1 + i];
    for (int i = 0; i < 3; ++i) {
      sh.trans[i] = r[10 + i];
      sh.half[i] = r[13 + i];
      sh.origin[i] = r[18 + i];
    }
    sh.radius = r[16];
    sh.half_height = r[17];
    sh.spacing = r[21];
    sh.lipschitz = r[22];
    sh.nx = static_cast<int64_t>(r[23]);
    sh.ny = static_cast<int64_t>(r[24]);
    sh.nz = static_cast<int64_t>(r[25]);
    sh.grid = grid + static_cast<int64_t>(r[26]);
    w.shapes.push_back(sh);
  }
  for (int i = 0; i < 3; ++i) w.gravity[i] = static_cast<S>(f[i]);
  w.h = static_cast<S>(f[3]);
  w.omega = static_cast<S>(f[4]);
  w.unload_velocity = static_cast<S>(f[5]);
  w.substeps = static_cast<int>(iv[0]);
  w.cap_static = static_cast<int>(iv[1]);
  w.cap_pair = static_cast<int>(iv[2]);
  return w;
}

}  // namespace dv

// threads: candidates are spread over this many threads (torch's intra-op pool is not used, so the
// simulator's parallelism does not depend on torch.set_num_threads).
// init: (B, N, 13) -> states (B, R, N, 13), extra and status (B, 4). mode 0: values only (extra
// empty); 1: extra = phi (B, R, 13N, 13N) = d state / d init (forward mode); 2: extra = the trace
// (B, steps * (substeps - k0), N, 13) of substep states that reverse mode (adjoint) reads. status:
// where a candidate diverged (run_candidate), checked only when floats carries the limits
// {reach, speed} after its first 6 numbers (mode 0 only).
std::vector<torch::Tensor> rollout(torch::Tensor init, int64_t steps, int64_t record_every, int64_t mode,
                                   std::vector<torch::Tensor> world, std::vector<double> floats,
                                   std::vector<int64_t> ints, int64_t threads) {
  TORCH_CHECK(init.device().is_cpu(), "the native simulator runs on the CPU");
  TORCH_CHECK(init.dim() == 3 && init.size(2) == 13, "init must be (B, N, 13)");
  TORCH_CHECK(steps >= 1 && record_every >= 1, "steps and record_every must be >= 1");
  TORCH_CHECK(mode >= 0 && mode <= 2, "mode must be 0 (values), 1 (Jacobians) or 2 (trace)");
  TORCH_CHECK(init.scalar_type() == torch::kFloat64, "the native simulator runs in float64");
  TORCH_CHECK(floats.size() == 6 || (floats.size() == 8 && mode == 0), "floats: gravity(3), h, omega, "
              "unload_velocity [, reach, speed (values only)]");
  init = init.contiguous();
  for (auto& t : world) t = t.contiguous();
  const int64_t b = init.size(0), n = init.size(1);
  const int64_t dim = 13 * n;
  const int64_t records = (steps + record_every - 1) / record_every;
  const bool with_jac = mode == 1;
  const int64_t per_step = ints.empty() ? 0 : ints[0] - dv::trace_first(record_every);
  auto states = torch::empty({b, records, n, 13}, init.options());
  torch::Tensor extra;
  if (mode == 1) extra = torch::empty({b, records, dim, dim}, init.options());
  else if (mode == 2) extra = torch::empty({b, steps * per_step, n, 13}, init.options());
  else extra = torch::empty({0}, init.options());
  auto status = torch::full({b, 4}, -1, init.options().dtype(torch::kInt64));
  {
    using S = double;
    const dv::World<S> w = dv::make_world<S>(world, floats, ints);
    TORCH_CHECK(w.n == n, "state and world disagree on the number of bodies");
    const S* in = init.data_ptr<S>();
    S* out = states.data_ptr<S>();
    S* ex = mode ? extra.data_ptr<S>() : nullptr;
    const int64_t ex_per = mode == 1 ? records * dim * dim : steps * per_step * dim;
    const S limit_values[2] = {floats.size() == 8 ? floats[6] : S(0), floats.size() == 8 ? floats[7] : S(0)};
    const S* limits = floats.size() == 8 ? limit_values : nullptr;
    int64_t* st = status.data_ptr<int64_t>();
    pybind11::gil_scoped_release no_gil;  // other Python threads (a server's event loop) run meanwhile
    dv::parallel_for(b, threads, [&](int64_t i) {
      dv::run_candidate<S>(w, in + i * dim, steps, record_every, with_jac, out + i * records * dim,
                           with_jac ? ex + i * ex_per : nullptr, limits, st + 4 * i,
                           mode == 2 ? ex + i * ex_per : nullptr);
    });
  }
  return {states, extra, status};
}

// Reverse mode: grad (B, R, N, 13) of the records of rollout(init, ..., mode 2) (states, trace)
// -> grad init (B, N, 13) = sum_t Phi_t^T grad_t, without forming Phi.
torch::Tensor adjoint(torch::Tensor init, torch::Tensor states, torch::Tensor trace, torch::Tensor grad,
                      int64_t steps, int64_t record_every, std::vector<torch::Tensor> world,
                      std::vector<double> floats, std::vector<int64_t> ints, int64_t threads) {
  TORCH_CHECK(init.dim() == 3 && init.size(2) == 13 && init.scalar_type() == torch::kFloat64 &&
              init.device().is_cpu(), "init must be (B, N, 13) float64 on the CPU");
  init = init.contiguous();
  states = states.contiguous();
  trace = trace.contiguous();
  grad = grad.to(torch::kFloat64).contiguous();
  for (auto& t : world) t = t.contiguous();
  const int64_t b = init.size(0), n = init.size(1);
  const int64_t dim = 13 * n;
  const int64_t records = (steps + record_every - 1) / record_every;
  const int64_t per_step = ints[0] - dv::trace_first(record_every);
  TORCH_CHECK(states.numel() == b * records * dim && grad.numel() == b * records * dim &&
              trace.numel() == b * steps * per_step * dim, "adjoint: states, trace or grad of the wrong size");
  auto out = torch::empty({b, n, 13}, init.options());
  {
    using S = double;
    const dv::World<S> w = dv::make_world<S>(world, floats, ints);
    TORCH_CHECK(w.n == n, "state and world disagree on the number of bodies");
    const S* in = init.data_ptr<S>();
    const S* rs = states.data_ptr<S>();
    const S* tr = trace.data_ptr<S>();
    const S* g = grad.data_ptr<S>();
    S* o = out.data_ptr<S>();
    pybind11::gil_scoped_release no_gil;
    dv::parallel_for(b, threads, [&](int64_t i) {
      dv::adjoint_candidate<S>(w, in + i * dim, steps, record_every, rs + i * records * dim,
                               tr + i * steps * per_step * dim, g + i * records * dim, o + i * dim);
    });
  }
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rollout", &rollout, "sphere-packing rollout with optional state Jacobians or trace (dejaview.sim.native)");
  m.def("adjoint", &adjoint, "reverse-mode gradient of a traced rollout (dejaview.sim.native)");
}
