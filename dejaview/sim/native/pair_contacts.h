// Which spheres of two bodies touch (select_pair) and the forces and torques between them
// (pair_wrench) (dejaview/sim/contacts.py in C++; dejaview.sim.native).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "contact_law.h"

namespace dv {

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
  const S stiff = contact_stiffness(w, w.mass_pair[pi]);
  const S unload = scaled_unload(w, w.unload_pair[pi]);
  const S inv_m = S(1) / w.mass[a] + S(1) / w.mass[b];
  const S h = w.h, uv = w.unload_velocity, mu = scaled_mu(w, w.mu_pair[pi]);
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
  for (int k = 0; k < m; ++k) loading[k] = loading_of(vn[k], dep[k], uv, w.omega);
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
