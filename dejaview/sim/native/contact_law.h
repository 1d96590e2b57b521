// The pieces of the contact model that static contacts and body pairs share: friction and the slip
// direction, the normal force, a sphere's centre, the closest point of a box body's surface, and a
// state row seeded as duals (dejaview/sim/contacts.py in C++; dejaview.sim.native).
#pragma once

#include <cmath>
#include <vector>

#include "dual.h"
#include "distance.h"

namespace dv {

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
// the contact is loading (restitution.loading: from its normal velocity vn and depth, the blend over a
// part of an impact's phase), then the force
template <typename T, typename S>
inline T loading_of(const T& vn, const T& depth, S unload_velocity, S omega) {
  const T lead = (S(schema::UNLOAD_WIDTH) * omega) * depth;
  return sigmoid(-(vn + S(schema::UNLOAD_LEAD) * lead) / (unload_velocity + lead));
}

// (the factor phi + (1 - phi) s cut off at zero: only a negative phi, restitution.UNLOAD_MIN, reaches it)
template <typename T, typename S>
inline T normal_force(const T& depth, const T& weight, const T& loading, S stiff, S unload) {
  const T g = unload + (1.0 - unload) * loading;
  return weight * stiff * depth * vmax(g, T(0.0));
}

struct Pick {
  int shape, sphere;
  double depth;
};

}  // namespace dv
