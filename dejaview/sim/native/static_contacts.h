// Which spheres of a body touch the static shapes (select_static, with exact culling) and the force
// and torque of those contacts (static_wrench), a line contact's roll stick included
// (dejaview/sim/contacts.py and line_contact.py in C++; dejaview.sim.native).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "box_edges.h"

namespace dv {

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
  // a moving static's keys say nothing (it moves, not only the body): its spheres are looked at anew
  const bool keyed = sh.path == nullptr;
  if (keyed && (floor[k] > thr || keymin[k] > thr)) return;
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
    if (!corners && keyed && std::max(kk[i], fl) > thr) {
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
  const S stiff = contact_stiffness(w, mass);
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
    mu[j] = scaled_mu(w, w.mu_static[a * w.k + picks[j].shape]);
    unload[j] = scaled_unload(w, w.unload_static[a * w.k + picks[j].shape]);
  }
  bool on_moving = false;  // touching a moving static: no roll stick (line_contact.py)
  for (int j = 0; j < m; ++j) {
    const T* n = nr + 3 * j;
    const T* r = ar + 3 * j;
    T wr[3], vel[3];
    cross3(om, r, wr);
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) vel[i] = v[i] + wr[i];
    const Shape<S>& sh = w.shapes[picks[j].shape];
    if (sh.path != nullptr) {  // relative to the moving static's point there
      T pt[3], sv[3];
      for (int i = 0; i < 3; ++i) pt[i] = x[i] + r[i];
      shape_point_velocity(sh, pt, sv);
      for (int i = 0; i < 3; ++i) vel[i] = vel[i] - sv[i];
      on_moving = on_moving || val(dep[j]) > 0;
    }
#pragma GCC unroll 3
    for (int i = 0; i < 3; ++i) velocity[i * m + j] = vel[i];
    vn[j] = dot3(vel, n);
  }
  for (int j = 0; j < m; ++j) loading[j] = loading_of(vn[j], dep[j], uv, w.omega);
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
  if (!is_box_body(w, a) && !on_moving &&
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

}  // namespace dv
