// The world as the engine reads it, static shapes' distances and the contact model: forces and
// torques of static contacts and body pairs (dejaview/sim/contacts.py in C++; dejaview.sim.native).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "dual.h"
#include "schema.h"

namespace dv {

// a body's state row (dejaview.sim.state.STATE_LAYOUT): x, q, v, w at these offsets
using schema::STATE_ANGULAR_VELOCITY;
using schema::STATE_LINEAR_VELOCITY;
using schema::STATE_ORIENTATION;
using schema::STATE_POSITION;
using schema::STATE_WIDTH;

// ------------------------------------------------------------------ world
template <typename S>
struct Shape {
  int kind;  // schema::KIND_*
  S rot[9], trans[3], half[3], radius, half_height, origin[3], spacing, lipschitz;
  const S* grid;
  int64_t nx, ny, nz;
};

template <typename S>
struct World {
  int n, s_max, k, p;
  std::vector<int> count;  // real spheres per body
  std::vector<S> reach;    // largest sphere-centre distance from the centre of mass, per body, and for a
                           // box its corners' (statics meet its corners, body pairs its surface)
  const S *mass, *inertia, *inv_inertia, *centers, *radii, *bound, *inv_i_min;
  std::vector<Shape<S>> shapes;
  const S *mu_static, *unload_static;  // (N, K)
  const int64_t* pairs;                 // (P, 2)
  const S *mu_pair, *unload_pair, *mass_pair;
  const S* box_half;             // (N, 3): a box body's half extents, 0 for the others
  const int64_t* pair_surface;   // (P): the box (0: a, 1: b) whose surface the other's spheres meet, or -1
  S gravity[3];
  S h, omega, unload_velocity;
  int substeps, cap_static, cap_pair;
};

// the time in which the roll stick stops a line's roll (line_contact.roll_stop_time): one substep at
// the default step, the contact's time scale ROLL_STOP_OMEGA_T / omega at finer ones
template <typename S>
S roll_stop_time(const World<S>& w) {
  return std::max(w.h, S(schema::ROLL_STOP_OMEGA_T) / w.omega);
}

// signed distance and outward normal of a world point, as StaticShape.distance (values, or a
// dual number of any width through distance() below); normal may be null: the distance alone
// (the same value, without the normal's divisions: contact selection)
static_assert(schema::KIND_COUNT == 5, "distance_direct has a branch per kind: add the new kind's");

template <typename T, typename S>
void distance_direct(const Shape<S>& sh, const T* pw, T& dist, T* normal) {
  T rel[3] = {pw[0] - sh.trans[0], pw[1] - sh.trans[1], pw[2] - sh.trans[2]};
  T p[3];
  for (int j = 0; j < 3; ++j) p[j] = rel[0] * sh.rot[j] + rel[1] * sh.rot[3 + j] + rel[2] * sh.rot[6 + j];
  T n[3];
  const S tiny2 = S(schema::NORMAL_EPS2);
  if (sh.kind == schema::KIND_PLANE) {  // plane z <= 0
    dist = p[2];
    n[0] = T(0); n[1] = T(0); n[2] = T(1);
  } else if (sh.kind == schema::KIND_BOX) {  // box
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
      if (normal != nullptr)
        for (int c = 0; c < 3; ++c) n[c] = out[c] / len * sign[c];
      dist = len;
    } else {
      for (int c = 0; c < 3; ++c) n[c] = T(c == axis ? sign[c] : S(0));
      dist = clamp_max0(q[axis]);
    }
  } else if (sh.kind == schema::KIND_SPHERE) {  // sphere
    T len = sqrt(dot3(p, p) + tiny2);
    if (normal != nullptr)
      for (int c = 0; c < 3; ++c) n[c] = p[c] / len;
    dist = len - sh.radius;
  } else if (sh.kind == schema::KIND_CYLINDER) {  // cylinder along z
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
  } else {  // grid (schema::KIND_GRID), trilinear
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
    if (val(elen) > S(schema::GRID_OUTSIDE)) {
      for (int c = 0; c < 3; ++c) n[c] = excess[c] / elen;
    } else {
      for (int c = 0; c < 3; ++c) n[c] = g[c] / sh.spacing;
    }
    dist = d + elen;
  }
  if (normal == nullptr) return;
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
using schema::NORMAL_EPS2;
using schema::SLIP_EPS;
using schema::TINY;
using schema::SMOOTH_MIN_POWER;

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
  thread_local std::vector<T> v[14];
  return v[slot];
}

// friction force (contacts.friction_force)
template <typename T, typename S>
__attribute__((always_inline)) inline void friction(const T* vt, const T& coulomb, const T& stick, T* out) {
  T speed = sqrt(dot3(vt, vt) + S(TINY));
  T b = stick * speed;
  T scale = vmax(coulomb, b) + S(TINY);
  T den = root8(pow8(coulomb / scale) + pow8(b / scale) + S(TINY)) * scale;
  T k = coulomb * stick / den;
  #pragma GCC unroll 3
  for (int c = 0; c < 3; ++c) out[c] = -(k * vt[c]);
}

// rotational inverse-mass term (contacts._inverse_mass) of one arm
template <typename T, typename S>
__attribute__((always_inline)) inline T inverse_mass(const T* arm, const T* t, const T* inv_w, S inv_i_min) {
  T u[3], iu[3];
  cross3(arm, t, u);
  matvec(inv_w, u, iu);
  T along = dot3(u, iu);
  T rest = (1.0 - dot3(t, t)) * dot3(arm, arm);
  return along + rest * inv_i_min;
}

template <typename T>
__attribute__((always_inline)) inline void slip_direction(const T* vt, T* t) {
  T den = sqrt(dot3(vt, vt) + SLIP_EPS * SLIP_EPS);
  #pragma GCC unroll 3
  for (int c = 0; c < 3; ++c) t[c] = vt[c] / den;
}

// a body's state row as duals, seeded as tangents offset..offset + STATE_WIDTH - 1
template <typename S, int W>
void seed_state(const S* s, Dual<S, W>* out, int offset) {
  for (int i = 0; i < STATE_WIDTH; ++i) {
    out[i] = Dual<S, W>(s[i]);
    out[i].d[offset + i] = S(1);
  }
}

// world centre of a body's sphere: x + R c
template <typename T, typename R, typename S>
inline void sphere_center(const T* x, const R* rot, const S* c, T* p) {
  for (int i = 0; i < 3; ++i) p[i] = x[i] + (c[0] * rot[3 * i] + c[1] * rot[3 * i + 1] + c[2] * rot[3 * i + 2]);
}

// A box body's surface as the partner of a sphere at world point p (contacts.box_partner): a
// sphere of radius `radius` centred at q = x + R cl (box centre x, world-from-body rot) whose
// surface touches the box's where the sphere's centre is nearest it. Outside the box: the closest
// point, cl = clamp(R^T (p - x), -half, half), radius 0. Inside (a penetration deeper than the
// sphere's radius): the nearest face k, cl = R^T (p - x) but cl_k = sign (half_k - deep), radius
// deep = 1 + |half|, so the distance |p - q| - radius is the box's signed distance either way and
// the normal its outward one. free[j]: 1 where cl_j is R^T (p - x)'s, 0 where it is a constant.
template <typename T, typename R, typename S>
inline void box_partner(const T* x, const R* rot, const S* half, const T* p, T* cl, T* q, S* free, S& radius) {
  T rel[3] = {p[0] - x[0], p[1] - x[1], p[2] - x[2]};
  T local[3];
  S over[3];
  bool outside = false;
  int nearest = 0;
  for (int j = 0; j < 3; ++j) {
    local[j] = rel[0] * rot[j] + rel[1] * rot[3 + j] + rel[2] * rot[6 + j];
    over[j] = std::abs(val(local[j])) - half[j];
    if (over[j] > 0) outside = true;
    if (over[j] > over[nearest]) nearest = j;
  }
  radius = S(0);
  for (int j = 0; j < 3; ++j) {
    if (outside && over[j] > 0) {
      cl[j] = T(val(local[j]) < 0 ? -half[j] : half[j]);
      free[j] = S(0);
    } else {
      cl[j] = local[j];
      free[j] = S(1);
    }
  }
  if (!outside) {
    const S deep = S(1) + std::sqrt(half[0] * half[0] + half[1] * half[1] + half[2] * half[2]);
    cl[nearest] = T(val(local[nearest]) < 0 ? deep - half[nearest] : half[nearest] - deep);
    free[nearest] = S(0);
    radius = deep;
  }
  for (int i = 0; i < 3; ++i) q[i] = x[i] + (cl[0] * rot[3 * i] + cl[1] * rot[3 * i + 1] + cl[2] * rot[3 * i + 2]);
}

// hysteretic spring normal force of one contact (contacts.normal_force), in two parts: how much
// the contact is loading (from its normal velocity vn), then the force
template <typename T, typename S>
inline T loading_of(const T& vn, S unload_velocity) { return sigmoid(-vn / unload_velocity); }

template <typename T, typename S>
inline T normal_force(const T& depth, const T& weight, const T& loading, S stiff, S unload) {
  return weight * stiff * depth * (unload + (1.0 - unload) * loading);
}

struct Pick {
  int shape, sphere;
  double depth;
};

// ------------------------------------------------------------------ static box edges
// A box body against a static box: the static's edges meet the body's exact faces at points
// EDGE_SPACING apart (box_edges.py, static_edge_points: per axis 0, 1, 2 its four edges at the
// other two axes' (-, -), (-, +), (+, -), (+, +) half extents, each edge_count points from -half to
// +half), and the body's spheres whose closest static point is on an edge or a corner are left
// out. A pick of such a point has sphere = -1 - (its index).
inline int edge_count(double half) {
  return std::max(2, static_cast<int>(std::nearbyint(2.0 * half / schema::EDGE_SPACING)) + 1);
}

// the static box's edge point e (world frame)
template <typename S>
void edge_point(const Shape<S>& sh, int e, S* out) {
  S local[3] = {S(0), S(0), S(0)};
  for (int axis = 0; axis < 3; ++axis) {
    const int n = edge_count(static_cast<double>(sh.half[axis]));
    if (e >= 4 * n) {
      e -= 4 * n;
      continue;
    }
    const int edge = e / n, i = e % n;
    const int o1 = axis == 0 ? 1 : 0, o2 = axis == 2 ? 1 : 2;
    local[axis] = S(i) * (S(2) * sh.half[axis] / S(n - 1)) - sh.half[axis];
    local[o1] = (edge / 2 ? S(1) : S(-1)) * sh.half[o1];
    local[o2] = (edge % 2 ? S(1) : S(-1)) * sh.half[o2];
    break;
  }
  for (int i = 0; i < 3; ++i)
    out[i] = local[0] * sh.rot[3 * i] + local[1] * sh.rot[3 * i + 1] + local[2] * sh.rot[3 * i + 2] + sh.trans[i];
}

// whether the static box's closest point to world point p is on an edge or a corner
template <typename S>
bool on_static_edge(const Shape<S>& sh, const S* p) {
  int outside = 0;
  for (int j = 0; j < 3; ++j) {
    const S l = (p[0] - sh.trans[0]) * sh.rot[j] + (p[1] - sh.trans[1]) * sh.rot[3 + j] +
                (p[2] - sh.trans[2]) * sh.rot[6 + j];
    if (std::abs(l) - sh.half[j] > 0) ++outside;
  }
  return outside >= 2;
}

// an edge point's contact with box body (half extents hb, centre x, world-from-body rot): its
// depth inside the box (min over the faces of half - |local|: the nearest face ax), the normal
// out of the static into the body (minus that face's normal) and the arm P - x
template <typename T, typename S>
void edge_contact(const S* P, const T* x, const T* rot, const S* hb, T& depth, T* n, T* arm, int* face = nullptr,
                  T* local = nullptr) {
  T rel[3], l[3];
  for (int i = 0; i < 3; ++i) rel[i] = P[i] - x[i];
  for (int j = 0; j < 3; ++j) l[j] = rel[0] * rot[j] + rel[1] * rot[3 + j] + rel[2] * rot[6 + j];
  int ax = 0;
  T best = hb[0] - abs(l[0]);
  for (int j = 1; j < 3; ++j) {
    T r = hb[j] - abs(l[j]);
    if (val(r) < val(best)) {
      best = r;
      ax = j;
    }
  }
  depth = relu(best);
  const S sg = val(l[ax]) < 0 ? S(-1) : S(1);
  for (int i = 0; i < 3; ++i) {
    n[i] = -sg * rot[3 * i + ax];
    arm[i] = rel[i];
  }
  if (face != nullptr) *face = ax;
  if (local != nullptr)
    for (int j = 0; j < 3; ++j) local[j] = l[j];
}

// box body a's picks of static box sh's edge points inside it, the cap deepest: per edge only the
// points where its line runs inside the body's box (clipped against the box's slabs in the body's
// frame, a point's margin either side; edge_contact decides), none while the box is farther from
// the static than its half diagonal
template <typename S>
void select_edges(const World<S>& w, int a, int k, const S* x, const S* rot, std::vector<Pick>& out) {
  const Shape<S>& sh = w.shapes[k];
  const S* hb = w.box_half + 3 * a;
  S dc;
  distance<S>(sh, x, dc, nullptr);
  if (dc > std::sqrt(hb[0] * hb[0] + hb[1] * hb[1] + hb[2] * hb[2])) return;
  thread_local std::vector<Pick> cand;
  cand.clear();
  int first = 0;
  for (int axis = 0; axis < 3; ++axis) {
    const int n = edge_count(static_cast<double>(sh.half[axis]));
    const S step = S(2) * sh.half[axis] / S(n - 1);
    for (int edge = 0; edge < 4; ++edge, first += n) {
      S p0[3], p1[3];
      edge_point(sh, first, p0);
      edge_point(sh, first + n - 1, p1);
      // the line p0 + t (p1 - p0) / |p1 - p0| in the body's frame: l(t) = l0 + t u
      S l0[3], u[3];
      const S len = S(2) * sh.half[axis];
      for (int j = 0; j < 3; ++j) {
        l0[j] = (p0[0] - x[0]) * rot[j] + (p0[1] - x[1]) * rot[3 + j] + (p0[2] - x[2]) * rot[6 + j];
        u[j] = ((p1[0] - p0[0]) * rot[j] + (p1[1] - p0[1]) * rot[3 + j] + (p1[2] - p0[2]) * rot[6 + j]) / len;
      }
      S t0 = S(0), t1 = len;
      for (int j = 0; j < 3 && t0 <= t1; ++j) {
        if (std::abs(u[j]) < S(schema::SLAB_PARALLEL)) {
          if (std::abs(l0[j]) >= hb[j]) t1 = S(-1);  // parallel to the slab and outside it
          continue;
        }
        S ta = (-hb[j] - l0[j]) / u[j], tb = (hb[j] - l0[j]) / u[j];
        if (ta > tb) std::swap(ta, tb);
        t0 = std::max(t0, ta);
        t1 = std::min(t1, tb);
      }
      if (t0 > t1) continue;
      const int i0 = std::max(0, static_cast<int>(std::floor(t0 / step)) - 1);
      const int i1 = std::min(n - 1, static_cast<int>(std::ceil(t1 / step)) + 1);
      for (int i = i0; i <= i1; ++i) {
        S P[3], depth, nn[3], arm[3];
        edge_point(sh, first + i, P);
        edge_contact<S, S>(P, x, rot, hb, depth, nn, arm);
        if (depth > 0) cand.push_back({k, -1 - (first + i), static_cast<double>(depth)});
      }
    }
  }
  if (static_cast<int>(cand.size()) > w.cap_static) {
    std::nth_element(cand.begin(), cand.begin() + w.cap_static, cand.end(),
                     [](const Pick& u, const Pick& v) { return u.depth > v.depth; });
    cand.resize(w.cap_static);
  }
  out.insert(out.end(), cand.begin(), cand.end());
}

template <typename S>
inline bool is_box_body(const World<S>& w, int a) {
  const S* hb = w.box_half + 3 * a;
  return hb[0] > 0 || hb[1] > 0 || hb[2] > 0;
}

// whether body a meets static shape k with its 8 corners (box_edges.CORNER_KINDS: a box body
// against a plane or a static box) rather than its packing
static_assert(schema::KIND_COUNT == 5, "corner_contacts names the flat kinds (box_edges.CORNER_KINDS)");

template <typename S>
inline bool corner_contacts(const World<S>& w, int a, int k) {
  const int kind = w.shapes[k].kind;
  return (kind == schema::KIND_PLANE || kind == schema::KIND_BOX) && is_box_body(w, a);
}

// sphere i of body a's static contacts: its centre c (3, body axes) and its radius; with corners
// (corner_contacts of the shape) the box's corner i (box_edges.box_corners: sign +1 along axis j
// where bit j of i is set, radius min(BOX_CORNER_RADIUS, min(half) / 4), centred that far
// inside), else its packing's sphere i
template <typename S>
inline S static_point(const World<S>& w, int a, bool corners, int i, S* c) {
  if (corners) {
    const S* hb = w.box_half + 3 * a;
    const S r = std::min(S(schema::BOX_CORNER_RADIUS), S(0.25) * std::min(hb[0], std::min(hb[1], hb[2])));
    for (int j = 0; j < 3; ++j) c[j] = ((i >> j) & 1 ? S(1) : S(-1)) * (hb[j] - r);
    return r;
  }
  const S* cc = w.centers + (static_cast<int64_t>(a) * w.s_max + i) * 3;
  for (int j = 0; j < 3; ++j) c[j] = cc[j];
  return w.radii[a * w.s_max + i];
}

// select_static's spheres of body a against static shape k (cand: the cap deepest), the bounds
// updated; box_edges: leave out the spheres whose closest point on the static box is on an edge.
// A box body's 8 corners against a flat shape (corner_contacts) have no keys of their own (the
// keys are the packing's): they are looked at every time they are not culled as a whole (floor,
// keymin)
template <typename S>
void select_spheres(const World<S>& w, int a, int k, const S* x, const S* rot, std::vector<Pick>& cand, S* key,
                    S* floor, S* keymin, S travel, bool box_edges) {
  cand.clear();
  const bool corners = corner_contacts(w, a, k);
  const int cnt = corners ? 8 : w.count[a];
  const Shape<S>& sh = w.shapes[k];
  const S shift = sh.lipschitz * travel;
  const S thr = S(schema::CLEAR_MARGIN) + shift;  // a key above this cannot touch now
  if (floor[k] > thr || keymin[k] > thr) return;
  S dc;
  distance<S>(sh, x, dc, nullptr);
  const S far = dc - sh.lipschitz * w.bound[a];
  if (far >= 0) {  // no sphere can reach the shape: d_i - r_i >= d_c - L (|c_i| + r_i) >= far
    floor[k] = far + shift;
    return;
  }
  S* kk = key + static_cast<int64_t>(k) * w.s_max;
  const S fl = floor[k];
  S low = std::numeric_limits<S>::infinity();
  for (int i = 0; i < cnt; ++i) {
    if (!corners && std::max(kk[i], fl) > thr) {
      low = std::min(low, kk[i]);
      continue;
    }
    S c[3], p[3], d;
    const S r = static_point(w, a, corners, i, c);
    sphere_center(x, rot, c, p);
    distance<S>(sh, p, d, nullptr);
    const S clear = (d - r) + shift;
    if (!corners) kk[i] = clear;
    low = std::min(low, clear);
    const S depth = r - d;
    if (depth > 0 && !(box_edges && on_static_edge(sh, p))) cand.push_back({k, i, static_cast<double>(depth)});
  }
  keymin[k] = low;
  // the torch engine selects among the packing and the corners (more than 8) where a box meets a
  // flat shape, among the packing where the packing holds more than the capacity
  if (static_cast<int>(cand.size()) > w.cap_static && (corners || w.s_max > w.cap_static)) {
    std::nth_element(cand.begin(), cand.begin() + w.cap_static, cand.end(),
                     [](const Pick& u, const Pick& v) { return u.depth > v.depth; });
    cand.resize(w.cap_static);
  }
}

// which spheres of body a touch the static shapes: per shape its cap deepest.
//
// Clearance bounds, in a frame that moves with the body's travel (the sum of how far any sphere
// centre of the body moved, substep after substep): key (K x s_max) holds, per shape and sphere,
// a lower bound on the clearance d - r when it was last looked at plus L * travel then (L the
// shape's Lipschitz bound), so key - L * travel is a lower bound now: a distance field drops by
// at most L times how far the point moved. A sphere whose bound stays above CLEAR_MARGIN cannot
// touch and is not looked at; floor (K) is a bound of the same kind for every sphere at once
// (from the body's centre), keymin (K) the smallest key. The picks are exactly those of a full
// scan.
using schema::CLEAR_MARGIN;

template <typename S>
void select_static(const World<S>& w, int a, const S* s, const S* rot, std::vector<Pick>& picks, S* key,
                   S* floor, S* keymin, S travel) {
  picks.clear();
  const S* x = s + STATE_POSITION;
  thread_local std::vector<Pick> cand;
  const bool box_body = is_box_body(w, a);
  for (int k = 0; k < w.k; ++k) {
    const Shape<S>& sh = w.shapes[k];
    const bool box_edges = box_body && sh.kind == schema::KIND_BOX;
    select_spheres(w, a, k, x, rot, cand, key, floor, keymin, travel, box_edges);
    picks.insert(picks.end(), cand.begin(), cand.end());
    if (box_edges) select_edges(w, a, k, x, rot, picks);  // after the spheres, as the torch engine
  }
}

// The roll stick of a line contact (line_contact.line_roll_stick): from the normal forces fn (m) of a
// body's static contact set, with weights w = dep / denom, arms ar and normals nr (3 m, rows of 3),
// the changes dfn (m) that make them max(fn + g, 0), the roll stopped within tau (roll_stop_time);
// false (dfn untouched) where the set is not elongated, so nothing changes
template <typename T, typename S>
bool line_roll_stick(int m, const T* dep, const T& denom, const T* nr, const T* ar, const T* fn, const T* om,
                     const T* iw, S inv_m, S tau, T* dfn) {
  T centre[3] = {T(0), T(0), T(0)}, mean_n[3] = {T(0), T(0), T(0)};
  for (int j = 0; j < m; ++j) {
    const T wj = dep[j] / denom;
    for (int i = 0; i < 3; ++i) {
      centre[i] = centre[i] + wj * ar[3 * j + i];
      mean_n[i] = mean_n[i] + wj * nr[3 * j + i];
    }
  }
  const T zlen = sqrt(dot3(mean_n, mean_n) + S(TINY));
  T z[3];
  for (int i = 0; i < 3; ++i) z[i] = mean_n[i] / zlen;
  T sec[9];
  for (int i = 0; i < 9; ++i) sec[i] = T(0);
  for (int j = 0; j < m; ++j) {
    const T wj = dep[j] / denom;
    T d[3];  // the arm from the centre
    for (int i = 0; i < 3; ++i) d[i] = ar[3 * j + i] - centre[i];
    const T sj = dot3(d, z);
    T p[3];
    for (int i = 0; i < 3; ++i) p[i] = d[i] - sj * z[i];
    for (int i = 0; i < 3; ++i)
      for (int k = 0; k < 3; ++k) sec[3 * i + k] = sec[3 * i + k] + wj * p[i] * p[k];
  }
  const T tr = sec[0] + sec[4] + sec[8];
  T sq = T(0);
  for (int i = 0; i < 9; ++i) sq = sq + sec[i] * sec[i];
  const T spread = sqrt(relu(S(2) * sq - tr * tr) + S(TINY));
  const T gate = relu((tr + spread - S(schema::LINE_ASPECT) * (tr - spread)) / (tr + spread + S(TINY)));
  if (!(val(tr) > S(schema::LINE_MIN_SPREAD)) || !(val(gate) > 0)) return false;
  // a a^T of the roll axis a = z x e: (P - (2 S - T P) / D) / 2, P = I - z z^T
  T roll[9];
  const T half_p = S(0.5) * (S(1) + tr / spread);
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k)
      roll[3 * i + k] = half_p * (S(i == k ? 1 : 0) - z[i] * z[k]) - sec[3 * i + k] / spread;
  T spin[3];
  matvec(roll, om, spin);
  std::vector<T>& qbuf = scratch<T>(11);  // (3 m) r x n of each contact
  std::vector<T>& ubuf = scratch<T>(12);  // (m) normal velocities from the roll
  qbuf.resize(3 * m);
  ubuf.resize(m);
  T mean_u = T(0);
  for (int j = 0; j < m; ++j) {  // u = (spin x r) . n = spin . (r x n)
    T* q = &qbuf[3 * j];
    cross3(ar + 3 * j, nr + 3 * j, q);
    ubuf[j] = dot3(spin, q);
    mean_u = mean_u + (dep[j] / denom) * ubuf[j];
  }
  for (int j = 0; j < m; ++j) {
    const T* q = &qbuf[3 * j];
    T iq[3];
    matvec(iw, q, iq);
    const T inv_mn = inv_m + dot3(q, iq);
    const T g = -(gate * (dep[j] / denom) * (ubuf[j] - mean_u)) / (inv_mn * tau);
    dfn[j] = relu(fn[j] + g) - fn[j];
  }
  return true;
}

// force and torque on body a from its picked static contacts; st = its state row as T
template <typename T, typename S>
void static_wrench(const World<S>& w, int a, const T* st, const std::vector<Pick>& picks, T* out) {
  for (int i = 0; i < 6; ++i) out[i] = T(0);
  // a NaN anywhere in the state makes the torch model's forces NaN (0 * NaN in every candidate
  // contact, touching or not): the same here, so a broken candidate reads as broken everywhere
  for (int i = 0; i < STATE_WIDTH && w.k > 0; ++i)
    if (std::isnan(val(st[i]))) {
      for (int j = 0; j < 6; ++j) out[j] = T(std::numeric_limits<S>::quiet_NaN());
      return;
    }
  const int m = static_cast<int>(picks.size());
  if (m == 0) return;
  const T* x = st + STATE_POSITION;
  const T* q = st + STATE_ORIENTATION;
  const T* v = st + STATE_LINEAR_VELOCITY;
  const T* om = st + STATE_ANGULAR_VELOCITY;
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
    if (pk.sphere < 0) {  // a static box's edge point against the box body's face
      S P[3];
      edge_point(w.shapes[pk.shape], -1 - pk.sphere, P);
      edge_contact<T, S>(P, x, rot, w.box_half + 3 * a, depth[j], &nrm[3 * j], &arm[3 * j]);
      total = total + depth[j];
      continue;
    }
    S c[3];
    const S r = static_point(w, a, corner_contacts(w, a, pk.shape), pk.sphere, c);
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
  const S h = w.h, uv = w.unload_velocity, inv_i_min = w.inv_i_min[a];
  // the contact law in stages, each a loop over the picks (the values' loops vectorise; the
  // sigmoid's exp, a library call, has its own loop), then the sums in pick order
  std::vector<T>& vn_buf = scratch<T>(7);  // (4, m) per pick vn, then its velocity (3)
  std::vector<T>& ftq_buf = scratch<T>(8);  // (6, m) per pick f (3) and its torque (3)
  std::vector<T>& loading_buf = scratch<T>(9);
  std::vector<S>& law = scratch<S>(10);  // per pick its shape's mu and unload
  vn_buf.resize(4 * m);
  ftq_buf.resize(6 * m);
  loading_buf.resize(m);
  law.resize(2 * m);
  T* __restrict vn = vn_buf.data();
  T* __restrict velocity = vn + m;
  T* __restrict ftq = ftq_buf.data();
  T* __restrict loading = loading_buf.data();
  S* __restrict mu = law.data();
  S* __restrict unload = mu + m;
  const T* __restrict dep = depth.data();
  const T* __restrict nr = nrm.data();
  const T* __restrict ar = arm.data();
  for (int j = 0; j < m; ++j) {
    mu[j] = w.mu_static[a * w.k + picks[j].shape];
    unload[j] = w.unload_static[a * w.k + picks[j].shape];
  }
  for (int j = 0; j < m; ++j) {
    const T* n = nr + 3 * j;
    const T* r = ar + 3 * j;
    T wr[3], vel[3];
    cross3(om, r, wr);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) {
      vel[i] = v[i] + wr[i];
      velocity[i * m + j] = vel[i];
    }
    vn[j] = dot3(vel, n);
  }
  for (int j = 0; j < m; ++j) loading[j] = loading_of(vn[j], uv);
  const T denom = total + tiny;
  // loop invariants as locals (no reloads through pointers the stores below might alias)
  T iw[9];
  for (int i = 0; i < 9; ++i) iw[i] = inv_w[i];
  // the normal forces first (ftq's rows hold fn n and its torque r x fn n for now) ...
#pragma GCC ivdep
  for (int j = 0; j < m; ++j) {
    const T* n = nr + 3 * j;
    const T* r = ar + 3 * j;
    T weight = dep[j] / denom;
    T fn = normal_force(dep[j], weight, loading[j], stiff, unload[j]);
    T f[3], tq[3];
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) f[i] = fn * n[i];
    cross3(r, f, tq);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) {
      ftq[i * m + j] = f[i];
      ftq[(3 + i) * m + j] = tq[i];
    }
    loading[j] = fn;  // loading is not needed again: the slot keeps fn
  }
  // ... their sum, the set's normal wrench, and the accelerations it gives (contacts.py,
  // "predicted slip": the friction acts on the slip the substep would end with)
  T fsum[3] = {T(0), T(0), T(0)}, tsum[3] = {T(0), T(0), T(0)};
  for (int j = 0; j < m; ++j)
    for (int i = 0; i < 3; ++i) {
      fsum[i] = fsum[i] + ftq[i * m + j];
      tsum[i] = tsum[i] + ftq[(3 + i) * m + j];
    }
  T acc[3], alpha[3];
  for (int i = 0; i < 3; ++i) acc[i] = fsum[i] * inv_m;
  matvec(iw, tsum, alpha);
#pragma GCC ivdep
  for (int j = 0; j < m; ++j) {
    const T* n = nr + 3 * j;
    const T* r = ar + 3 * j;
    T vt[3], t[3], ft[3], f[3], tq[3], dv[3];
    cross3(alpha, r, dv);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) dv[i] = acc[i] + dv[i];
    const T dvn = dot3(dv, n);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) vt[i] = velocity[i * m + j] - vn[j] * n[i] + h * (dv[i] - dvn * n[i]);
    T weight = dep[j] / denom;
    const T fn = loading[j];
    slip_direction(vt, t);
    T inv_mass = inv_m + inverse_mass(r, t, iw, inv_i_min);
    T stick = weight / (inv_mass * h);
    friction<T, S>(vt, mu[j] * fn, stick, ft);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) f[i] = fn * n[i] + ft[i];
    cross3(r, f, tq);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) {
      ftq[i * m + j] = f[i];  // (6, m): one row per component
      ftq[(3 + i) * m + j] = tq[i];
    }
  }
  // the roll stick of a line contact: its changes of the normal forces (loading's slot holds fn)
  std::vector<T>& dfn = scratch<T>(13);
  dfn.resize(m);
  // (not for a box body: it meets flat shapes with its exact corners, line_contact.py)
  if (!is_box_body(w, a) &&
      line_roll_stick<T, S>(m, dep, denom, nr, ar, loading, om, iw, inv_m, roll_stop_time(w), dfn.data()))
    for (int j = 0; j < m; ++j) {
      T f[3], tq[3];
      for (int i = 0; i < 3; ++i) f[i] = dfn[j] * nr[3 * j + i];
      cross3(ar + 3 * j, f, tq);
      for (int i = 0; i < 3; ++i) {
        ftq[i * m + j] = ftq[i * m + j] + f[i];
        ftq[(3 + i) * m + j] = ftq[(3 + i) * m + j] + tq[i];
      }
    }
  for (int j = 0; j < m; ++j)
    for (int i = 0; i < 6; ++i) out[i] = out[i] + ftq[i * m + j];
}

// column k of a pair's (9, m) forces: f (on b; -f on a), its torque on a (arm_a x -f) and on b
template <typename T>
__attribute__((always_inline)) inline void store_pair_force(const T* f, const T* ra, const T* rb, T* fts, int m,
                                                            int k) {
  T neg[3], ta[3], tb[3];
#pragma GCC unroll 3
  for (int i = 0; i < 3; ++i) neg[i] = -f[i];
  cross3(ra, neg, ta);
  cross3(rb, f, tb);
#pragma GCC unroll 3
  for (int i = 0; i < 3; ++i) {
    fts[i * m + k] = f[i];
    fts[(3 + i) * m + k] = ta[i];
    fts[(6 + i) * m + k] = tb[i];
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

// the capacity's deepest picks of a body pair, the others dropped (contacts.deepest)
inline void keep_deepest(std::vector<PairPick>& picks, int cap) {
  if (static_cast<int>(picks.size()) <= cap) return;
  std::nth_element(picks.begin(), picks.begin() + cap, picks.end(),
                   [](const PairPick& u, const PairPick& v) { return u.depth > v.depth; });
  picks.resize(cap);
}

// Returns a lower bound on the clearance |p_i - p_j| - r_i - r_j of every sphere pair (exact
// distances for the pairs looked at, the mid phase's margin for the others).
template <typename S>
S select_pair(const World<S>& w, int pi, int a, int b, const S* sa, const S* sb, const S* ra, const S* rb,
              std::vector<PairPick>& picks) {
  picks.clear();
  const S* xa = sa + STATE_POSITION;
  const S* xb = sb + STATE_POSITION;
  S dx[3] = {xa[0] - xb[0], xa[1] - xb[1], xa[2] - xb[2]};
  const S centres = std::sqrt(dot3(dx, dx));
  if (!(centres < w.bound[a] + w.bound[b])) return centres - (w.bound[a] + w.bound[b]);
  // mid phase: sphere i of a can touch some sphere j of b only if |p_i - x_b| < r_i + bound_b
  // (|p_i - p_j| < r_i + r_j and |p_j - x_b| + r_j <= bound_b); likewise for b's spheres. A
  // sphere left out is at least |p_i - x_b| - r_i - bound_b >= 0 clear of every sphere of b.
  S bound = std::numeric_limits<S>::infinity();
  auto near = [&](int body, const S* x, const S* rot, const S* other, S other_bound,
                  std::vector<int>& ids, std::vector<S>& pts) {
    ids.clear();
    pts.clear();
    for (int i = 0; i < w.count[body]; ++i) {
      const S* c = w.centers + (static_cast<int64_t>(body) * w.s_max + i) * 3;
      S p[3], d[3];
      sphere_center(x, rot, c, p);
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
  const int64_t side = w.pair_surface[pi];
  if (side >= 0) {  // the other body's spheres against the box's surface (j or i = -1: the box)
    const int box = side == 0 ? a : b, other = side == 0 ? b : a;
    const S* sbox = side == 0 ? xa : xb;
    const S* sother = side == 0 ? xb : xa;
    const S* rbox = side == 0 ? ra : rb;
    const S* rother = side == 0 ? rb : ra;
    const S* half = w.box_half + 3 * box;
    for (int i = 0; i < w.count[other]; ++i) {
      const S* c = w.centers + (static_cast<int64_t>(other) * w.s_max + i) * 3;
      S p[3], cl[3], q[3], free[3], deep;
      sphere_center(sother, rother, c, p);
      box_partner(sbox, rbox, half, p, cl, q, free, deep);
      S df[3] = {p[0] - q[0], p[1] - q[1], p[2] - q[2]};
      const S depth = w.radii[other * w.s_max + i] + deep - std::sqrt(dot3(df, df));
      if (depth > 0) picks.push_back(side == 0 ? PairPick{-1, i, static_cast<double>(depth)}
                                               : PairPick{i, -1, static_cast<double>(depth)});
      bound = std::min(bound, -depth);
    }
    keep_deepest(picks, w.cap_pair);
    return bound;
  }
  std::vector<int>& ia = pair_ids_a<S>();
  std::vector<int>& ib = pair_ids_b<S>();
  std::vector<S>& pa = pair_pts_a<S>();
  std::vector<S>& pb = pair_pts_b<S>();
  near(a, xa, ra, xb, w.bound[b], ia, pa);
  if (ia.empty()) return bound;
  near(b, xb, rb, xa, w.bound[a], ib, pb);
  for (size_t u = 0; u < ia.size(); ++u) {
    const S r_i = w.radii[a * w.s_max + ia[u]];
    for (size_t v = 0; v < ib.size(); ++v) {
      S df[3] = {pb[3 * v] - pa[3 * u], pb[3 * v + 1] - pa[3 * u + 1], pb[3 * v + 2] - pa[3 * u + 2]};
      const S depth = r_i + w.radii[b * w.s_max + ib[v]] - std::sqrt(dot3(df, df));
      if (depth > 0) picks.push_back({ia[u], ib[v], static_cast<double>(depth)});
      bound = std::min(bound, -depth);
    }
  }
  keep_deepest(picks, w.cap_pair);
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
  quat_to_matrix(st_a + STATE_ORIENTATION, rot_a);
  quat_to_matrix(st_b + STATE_ORIENTATION, rot_b);
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
    T pa[3], pb[3], diff[3], cl[3];
    S r_a = 0, r_b = 0;
    if (picks[k].i >= 0) {
      sphere_center(st_a + STATE_POSITION, rot_a, w.centers + (static_cast<int64_t>(a) * w.s_max + picks[k].i) * 3,
                    pa);
      r_a = w.radii[a * w.s_max + picks[k].i];
    }
    if (picks[k].j >= 0) {
      sphere_center(st_b + STATE_POSITION, rot_b, w.centers + (static_cast<int64_t>(b) * w.s_max + picks[k].j) * 3,
                    pb);
      r_b = w.radii[b * w.s_max + picks[k].j];
    } else {  // b's box surface as a's sphere's partner (box_partner)
      S free[3];
      box_partner(st_b + STATE_POSITION, rot_b, w.box_half + 3 * b, pa, cl, pb, free, r_b);
    }
    if (picks[k].i < 0) {  // a's box surface
      S free[3];
      box_partner(st_a + STATE_POSITION, rot_a, w.box_half + 3 * a, pb, cl, pa, free, r_a);
    }
    for (int i = 0; i < 3; ++i) diff[i] = pb[i] - pa[i];
    T dist = sqrt(dot3(diff, diff) + S(NORMAL_EPS2));
    for (int i = 0; i < 3; ++i) nrm[3 * k + i] = diff[i] / dist;
    depth[k] = relu((r_a + r_b) - dist);
    for (int i = 0; i < 3; ++i) {
      T point = pa[i] + nrm[3 * k + i] * r_a;
      arm_a[3 * k + i] = point - st_a[STATE_POSITION + i];
      arm_b[3 * k + i] = point - st_b[STATE_POSITION + i];
    }
    total = total + depth[k];
  }
  const S tiny = std::numeric_limits<S>::min();
  const S stiff = w.mass_pair[pi] * w.omega * w.omega;
  const S unload = w.unload_pair[pi];
  const S inv_m = S(1) / w.mass[a] + S(1) / w.mass[b];
  const S h = w.h, uv = w.unload_velocity, mu = w.mu_pair[pi];
  const S imin_a = w.inv_i_min[a], imin_b = w.inv_i_min[b];
  // in stages, as static_wrench: the relative normal velocity, the loading (exp), the law
  // (vectorised for values), the sums in pick order
  std::vector<T>& vn_buf = scratch<T>(7);  // (4, m) per pick vn, then the relative velocity (3)
  std::vector<T>& loading_buf = scratch<T>(9);
  std::vector<T>& fts_buf = scratch<T>(8);  // (9, m): f (3), the torques on a (3) and b (3)
  vn_buf.resize(4 * m);
  loading_buf.resize(m);
  fts_buf.resize(9 * m);
  T* __restrict vn = vn_buf.data();
  T* __restrict velocity = vn + m;
  T* __restrict loading = loading_buf.data();
  T* __restrict fts = fts_buf.data();
  const T* __restrict dep = depth.data();
  const T* __restrict nr = nrm.data();
  const T* __restrict aa = arm_a.data();
  const T* __restrict ab = arm_b.data();
  T va[3], vb[3], wa0[3], wb0[3], iwa[9], iwb[9];
  for (int i = 0; i < 3; ++i) {
    va[i] = st_a[STATE_LINEAR_VELOCITY + i];
    vb[i] = st_b[STATE_LINEAR_VELOCITY + i];
    wa0[i] = st_a[STATE_ANGULAR_VELOCITY + i];
    wb0[i] = st_b[STATE_ANGULAR_VELOCITY + i];
  }
  for (int i = 0; i < 9; ++i) {
    iwa[i] = iw_a[i];
    iwb[i] = iw_b[i];
  }
  for (int k = 0; k < m; ++k) {
    T wa[3], wb[3], vrel[3];
    cross3(wa0, aa + 3 * k, wa);
    cross3(wb0, ab + 3 * k, wb);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) {
      vrel[i] = (vb[i] + wb[i]) - (va[i] + wa[i]);
      velocity[i * m + k] = vrel[i];
    }
    vn[k] = dot3(vrel, nr + 3 * k);
  }
  for (int k = 0; k < m; ++k) loading[k] = loading_of(vn[k], uv);
  const T denom = total + tiny;
  // the normal forces first (fts's rows hold fn n and its torques for now), their sums, and the
  // relative acceleration they give (static_wrench: the predicted slip)
#pragma GCC ivdep
  for (int k = 0; k < m; ++k) {
    const T* n = nr + 3 * k;
    const T* ra = aa + 3 * k;
    const T* rb = ab + 3 * k;
    T weight = dep[k] / denom;
    T fn = normal_force(dep[k], weight, loading[k], stiff, unload);
    T f[3];
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) f[i] = fn * n[i];
    store_pair_force(f, ra, rb, fts, m, k);
    loading[k] = fn;  // the slot keeps fn
  }
  T fsum[3] = {T(0), T(0), T(0)}, tsa[3] = {T(0), T(0), T(0)}, tsb[3] = {T(0), T(0), T(0)};
  for (int k = 0; k < m; ++k)
    for (int i = 0; i < 3; ++i) {
      fsum[i] = fsum[i] + fts[i * m + k];
      tsa[i] = tsa[i] + fts[(3 + i) * m + k];
      tsb[i] = tsb[i] + fts[(6 + i) * m + k];
    }
  T acc[3], alpha_a[3], alpha_b[3];
  for (int i = 0; i < 3; ++i) acc[i] = fsum[i] * inv_m;  // b's acceleration relative to a's
  matvec(iwa, tsa, alpha_a);
  matvec(iwb, tsb, alpha_b);
#pragma GCC ivdep
  for (int k = 0; k < m; ++k) {
    const T* n = nr + 3 * k;
    const T* ra = aa + 3 * k;
    const T* rb = ab + 3 * k;
    T vt[3], t[3], ft[3], dva[3], dvb[3], dv[3];
    cross3(alpha_a, ra, dva);
    cross3(alpha_b, rb, dvb);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) dv[i] = acc[i] + dvb[i] - dva[i];
    const T dvn = dot3(dv, n);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) vt[i] = velocity[i * m + k] - vn[k] * n[i] + h * (dv[i] - dvn * n[i]);
    T weight = dep[k] / denom;
    const T fn = loading[k];
    slip_direction(vt, t);
    T inv_mass = inv_m + inverse_mass(ra, t, iwa, imin_a) + inverse_mass(rb, t, iwb, imin_b);
    T stick = weight / (inv_mass * h);
    friction<T, S>(vt, mu * fn, stick, ft);
    T f[3];
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) f[i] = fn * n[i] + ft[i];
    store_pair_force(f, ra, rb, fts, m, k);
  }
  for (int k = 0; k < m; ++k)
    for (int i = 0; i < 3; ++i) {
      out[i] = out[i] - fts[i * m + k];
      out[3 + i] = out[3 + i] + fts[(3 + i) * m + k];
      out[6 + i] = out[6 + i] + fts[i * m + k];
      out[9 + i] = out[9 + i] + fts[(6 + i) * m + k];
    }
}

}  // namespace dv
