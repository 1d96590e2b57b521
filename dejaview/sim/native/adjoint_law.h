// Reverse mode by hand (adjoint.h): small vector-Jacobian products and the contact law of one
// contact, shared by static contacts and body pairs (dejaview.sim.native).
#pragma once

#include <cmath>
#include <vector>

#include "contacts.h"
#include "dual.h"

namespace dv {

// ------------------------------------------------------------------ small pieces
template <typename S> inline void add_cross(const S* a, const S* b, S* out) {  // out += a x b
  out[0] += a[1] * b[2] - a[2] * b[1];
  out[1] += a[2] * b[0] - a[0] * b[2];
  out[2] += a[0] * b[1] - a[1] * b[0];
}

template <typename S> inline S pow7(S x) { const S x2 = x * x, x4 = x2 * x2; return x4 * x2 * x; }

// qb (4) += (d R(q) / d q)^T rb, R = quat_to_matrix(q) (dual.h)
template <typename S> inline void quat_to_matrix_vjp(const S* q, const S* rb, S* qb) {
  const S w = q[0], x = q[1], y = q[2], z = q[3];
  qb[0] += 2 * (-z * rb[1] + y * rb[2] + z * rb[3] - x * rb[5] - y * rb[6] + x * rb[7]);
  qb[1] += 2 * (y * rb[1] + z * rb[2] + y * rb[3] - 2 * x * rb[4] - w * rb[5] + z * rb[6] + w * rb[7] -
                2 * x * rb[8]);
  qb[2] += 2 * (-2 * y * rb[0] + x * rb[1] + w * rb[2] + x * rb[3] + z * rb[5] - w * rb[6] + z * rb[7] -
                2 * y * rb[8]);
  qb[3] += 2 * (-2 * z * rb[0] - w * rb[1] + x * rb[2] + w * rb[3] - 2 * z * rb[4] + y * rb[5] + x * rb[6] +
                y * rb[7]);
}

// rb (9) += d (R A R^T) / d R contracted with ob (9): ob R A^T + ob^T R A (A body-frame, constant)
template <typename S> inline void rotate_tensor_vjp(const S* r, const S* a, const S* ob, S* rb) {
  S rat[9], ra[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      rat[3 * i + j] = r[3 * i] * a[3 * j] + r[3 * i + 1] * a[3 * j + 1] + r[3 * i + 2] * a[3 * j + 2];
      ra[3 * i + j] = r[3 * i] * a[j] + r[3 * i + 1] * a[3 + j] + r[3 * i + 2] * a[6 + j];
    }
  for (int m = 0; m < 3; ++m)
    for (int n = 0; n < 3; ++n) {
      S acc = 0;
      for (int j = 0; j < 3; ++j) acc += ob[3 * m + j] * rat[3 * j + n] + ob[3 * j + m] * ra[3 * j + n];
      rb[3 * m + n] += acc;
    }
}

// ------------------------------------------------------------------ the contact law
// One contact's force f (3) from its normal n (pointing from the body that gets -f to the one that
// gets +f), depth, weight, relative velocity vel of the +f side, and the inverse-mass terms of its
// one or two arms (contact_law.h: normal_force, slip_direction, inverse_mass, friction), with the
// values the way back needs.
template <typename S>
struct ContactLaw {
  int arms;  // 1: a static contact, 2: a body pair
  S n[3], depth, weight, vel[3], stiff, unload, mu, inv_m, h, unload_velocity, omega;
  const S* arm[2];
  const S* inv_w[2];
  S inv_i_min[2];
  // forward values
  S vn, vt[3], spread, loading, g, fn;
  bool cut;  // the factor g was below zero and is cut off there (normal_force)
  S dv[3], dvn, pred[3], vs[3];  // the predicted slip: its rate of change, then vs = vt + pred
  S tden, t[3], u[2][3], iu[2][3], arm2[2], im, stick;
  S coulomb, speed, b, scale, uu, vv, pp, rt, den, k;
  bool b_wins;
  S f[3];
  // the way back's cotangents of the law's material (mu, stiff, unload), for the physics' gradient
  mutable S mub = S(0), stiffb = S(0), unloadb = S(0);

  // The values run forward_normal, then predict (once the set's normal forces are known), then
  // forward_friction; the way back runs backward_friction, predict_backward, then (once the
  // set's sums have their cotangents) backward_normal.

  // the normal force fn (and vn, vt)
  void forward_normal() {
    vn = dot3(vel, n);
    for (int i = 0; i < 3; ++i) vt[i] = vel[i] - vn * n[i];
    const S lead = (S(schema::UNLOAD_WIDTH) * omega) * depth;  // loading_of (contact_law.h)
    spread = unload_velocity + lead;
    loading = sigmoid(-(vn + S(schema::UNLOAD_LEAD) * lead) / spread);
    g = unload + (S(1) - unload) * loading;
    cut = g < S(0);
    if (cut) g = S(0);
    fn = weight * stiff * depth * g;
  }

  // the slip's predicted change over a substep of length h, from dv_in (3), the rate of change of
  // the contact's (relative) velocity that the set's normal forces give: pred = h (dv - (dv.n) n)
  void predict(const S* dv_in, S h) {
    for (int i = 0; i < 3; ++i) dv[i] = dv_in[i];
    dvn = dot3(dv, n);
    for (int i = 0; i < 3; ++i) pred[i] = h * (dv[i] - dvn * n[i]);
  }

  // its vjp: from vsb (3), the slip's cotangent (= pred's), to dvb (3, set) and nb (added to)
  void predict_backward(const S* vsb, S h, S* dvb, S* nb) const {
    const S vsbn = dot3(vsb, n);
    for (int i = 0; i < 3; ++i) {
      dvb[i] = h * (vsb[i] - vsbn * n[i]);
      nb[i] -= h * (vsbn * dv[i] + dvn * vsb[i]);
    }
  }

  // the friction on the slip vs = vt + pred, and the force f
  void forward_friction() {
    for (int i = 0; i < 3; ++i) vs[i] = vt[i] + pred[i];
    tden = std::sqrt(dot3(vs, vs) + SLIP_EPS * SLIP_EPS);
    for (int i = 0; i < 3; ++i) t[i] = vs[i] / tden;
    im = inv_m;
    const S rest_t = S(1) - dot3(t, t);
    for (int s = 0; s < arms; ++s) {
      cross3(arm[s], t, u[s]);
      matvec(inv_w[s], u[s], iu[s]);
      arm2[s] = dot3(arm[s], arm[s]);
      im += dot3(u[s], iu[s]) + rest_t * arm2[s] * inv_i_min[s];
    }
    stick = weight / (im * h);
    coulomb = mu * fn;
    speed = std::sqrt(dot3(vs, vs) + S(TINY));
    b = stick * speed;
    b_wins = b > coulomb;
    scale = (b_wins ? b : coulomb) + S(TINY);
    uu = coulomb / scale;
    vv = b / scale;
    pp = pow8(uu) + pow8(vv) + S(TINY);
    rt = root8(pp);
    den = rt * scale;
    k = coulomb * stick / den;
    for (int i = 0; i < 3; ++i) f[i] = fn * n[i] - k * vs[i];
  }

  // the friction's part: from fb (3) to fnb and vsb (3) (set), nb, armb[s], ginv_w[s] (added to),
  // weightb (set: through the stick limit)
  void backward_friction(const S* fb, S* nb, S* const* armb, S* const* ginv_w, S& fnb, S* vtb,
                         S& weightb) const {
    fnb = dot3(fb, n);
    for (int i = 0; i < 3; ++i) nb[i] += fn * fb[i];
    const S kb = -dot3(fb, vs);
    for (int i = 0; i < 3; ++i) vtb[i] = -k * fb[i];
    // friction: k = coulomb * stick / den, den = root8(pp) * scale, pp = uu^8 + vv^8 + TINY
    S cb = kb * stick / den;
    S stickb = kb * coulomb / den;
    const S denb = -kb * k / den;
    const S rtb = denb * scale;
    S scaleb = denb * rt;
    const S ppb = rtb * S(0.125) * rt / pp;
    const S uub = ppb * S(8) * pow7(uu);
    const S vvb = ppb * S(8) * pow7(vv);
    cb += uub / scale;
    scaleb -= uub * uu / scale;
    S bb = vvb / scale;
    scaleb -= vvb * vv / scale;
    if (b_wins) bb += scaleb; else cb += scaleb;
    stickb += bb * speed;
    const S speedb = bb * stick;
    for (int i = 0; i < 3; ++i) vtb[i] += speedb * vs[i] / speed;
    fnb += cb * mu;
    mub = cb * fn;
    // stick = weight / (im h)
    weightb = stickb / (im * h);
    const S imb = -stickb * stick / im;
    // inverse mass: sum over arms of u.(inv_w u) + (1 - t.t) |arm|^2 inv_i_min, u = arm x t
    S tb[3] = {0, 0, 0};
    const S rest_t = S(1) - dot3(t, t);
    for (int s = 0; s < arms; ++s) {
      S ub[3], wtu[3];
      matvec_t(inv_w[s], u[s], wtu);
      for (int i = 0; i < 3; ++i) ub[i] = imb * (iu[s][i] + wtu[i]);
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) ginv_w[s][3 * i + j] += imb * u[s][i] * u[s][j];
      const S restb = imb * inv_i_min[s];
      for (int i = 0; i < 3; ++i) {
        tb[i] -= restb * arm2[s] * S(2) * t[i];
        armb[s][i] += restb * rest_t * S(2) * arm[s][i];
      }
      add_cross(t, ub, armb[s]);  // u = arm x t: armb += t x ub, tb += ub x arm
      add_cross(ub, arm[s], tb);
    }
    // t = vs / sqrt(vs.vs + eps^2)
    const S tv = dot3(tb, vs) / (tden * tden * tden);
    for (int i = 0; i < 3; ++i) vtb[i] += tb[i] / tden - vs[i] * tv;
  }

  // gp (3) += the gradient of the way back's loss with respect to the logs of the World's physics
  // factors (mu_scale, unload_scale, stiff_scale: World), from the cotangents the two passes left
  // (an unloading factor held at 1 by scaled_unload has none; below it, d phi' / d log f = phi' - m)
  void add_material_gradient(S* gp) const {
    gp[0] += mub * mu;
    if (unload < S(1)) gp[1] += unloadb * (unload - S(schema::UNLOAD_MIN));
    gp[2] += stiffb * stiff;
  }

  // backward_normal where y = fn n also entered the set's sums, with cotangent yb (3)
  void backward_normal_and_sum(S fnb, const S* yb, const S* vtb, S* nb, S* velb, S& depthb,
                               S& weightb) const {
    for (int i = 0; i < 3; ++i) nb[i] += fn * yb[i];
    backward_normal(fnb + dot3(yb, n), vtb, nb, velb, depthb, weightb);
  }

  // the normal force's part: from fnb and vtb (3) to nb, velb (added to), depthb (set), weightb
  // (added to)
  void backward_normal(S fnb, const S* vtb_in, S* nb, S* velb, S& depthb, S& weightb) const {
    S vtb[3] = {vtb_in[0], vtb_in[1], vtb_in[2]};
    // fn = weight stiff depth g, g = max(0, unload + (1 - unload) s),
    // s = sigmoid(a), a = -(vn + beta L) / (uv + L), L = w omega depth
    weightb += fnb * stiff * depth * g;
    stiffb = fnb * weight * depth * g;
    const S gb = cut ? S(0) : fnb * weight * stiff * depth;
    unloadb = gb * (S(1) - loading);
    const S loadingb = gb * (S(1) - unload);
    const S ab = loadingb * loading * (S(1) - loading);
    S vnb = -ab / spread;
    // da/dL = ((vn + beta L) - beta spread) / spread^2 = (vn - beta uv) / spread^2
    const S beta = S(schema::UNLOAD_LEAD);
    const S leadb = ab * (vn - beta * unload_velocity) / (spread * spread);
    depthb = fnb * weight * stiff * g + leadb * (S(schema::UNLOAD_WIDTH) * omega);
    // vt = vel - vn n, vn = vel . n
    vnb -= dot3(vtb, n);
    for (int i = 0; i < 3; ++i) {
      nb[i] += -vn * vtb[i] + vnb * vel[i];
      velb[i] += vtb[i] + vnb * n[i];
    }
  }
};

}  // namespace dv
