// Reverse mode of one substep's pieces, written by hand (dejaview.sim.native; issue 25): vector-
// Jacobian products of the static contacts' wrench, a body pair's wrench and the integration, for
// the adjoint lam <- J^T lam of rollout.cpp's substep_adjoint.
//
// The forward-mode dual passes of contacts.h and integrate.h (Dual<13>, <26>, <19>) compute whole
// Jacobians, 13 to 26 tangents per operation; the adjoint needs only their product with one
// cotangent, which reverse mode gets in a few times the cost of the values. Each piece below runs
// its values forward (the same formulas as the templates, on doubles), keeps what the way back
// needs, and walks back from the cotangent. The dual passes stay the reference: forward mode uses
// them, and the adjoint must agree with them (tests/sim/test_native_gradients.py,
// tests/sim/test_native_schema.py).
//
// Notation: for y = f(x), xb (x-bar) is the cotangent d L / d x; a function's "vjp" adds
// (d f / d x)^T yb to xb. Kinks follow the dual code (relu passes nothing at 0, vmax sends the
// derivative to the larger argument, b on a tie).
#pragma once

#include <cmath>
#include <limits>
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
// one or two arms (contacts.h: normal_force, slip_direction, inverse_mass, friction), with the
// values the way back needs.
template <typename S>
struct ContactLaw {
  int arms;  // 1: a static contact, 2: a body pair
  S n[3], depth, weight, vel[3], stiff, unload, mu, inv_m, h, unload_velocity;
  const S* arm[2];
  const S* inv_w[2];
  S inv_i_min[2];
  // forward values
  S vn, vt[3], loading, g, fn;
  S dv[3], dvn, pred[3], vs[3];  // the predicted slip: its rate of change, then vs = vt + pred
  S tden, t[3], u[2][3], iu[2][3], arm2[2], im, stick;
  S coulomb, speed, b, scale, uu, vv, pp, rt, den, k;
  bool b_wins;
  S f[3];

  // The values run forward_normal, then predict (once the set's normal forces are known), then
  // forward_friction; the way back runs backward_friction, predict_backward, then (once the
  // set's sums have their cotangents) backward_normal.

  // the normal force fn (and vn, vt)
  void forward_normal() {
    vn = dot3(vel, n);
    for (int i = 0; i < 3; ++i) vt[i] = vel[i] - vn * n[i];
    loading = sigmoid(-vn / unload_velocity);
    g = unload + (S(1) - unload) * loading;
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
    // fn = weight stiff depth g, g = unload + (1 - unload) sigmoid(-vn / uv)
    weightb += fnb * stiff * depth * g;
    depthb = fnb * weight * stiff * g;
    const S loadingb = fnb * weight * stiff * depth * (S(1) - unload);
    S vnb = -loadingb * loading * (S(1) - loading) / unload_velocity;
    // vt = vel - vn n, vn = vel . n
    vnb -= dot3(vtb, n);
    for (int i = 0; i < 3; ++i) {
      nb[i] += -vn * vtb[i] + vnb * vel[i];
      velb[i] += vtb[i] + vnb * n[i];
    }
  }
};

// ------------------------------------------------------------------ the roll stick of a line contact
// contacts.h's line_roll_stick on values, with what the way back needs, and its vjp. Inputs per
// contact j: weight w_j, arm r_j, normal n_j, normal force fn_j; per set: the spin om, the world
// inverse inertia iw, the stop time tau (roll_stop_time); out: dfn_j = max(fn_j + g_j, 0) - fn_j.
template <typename S>
struct RollStick {
  struct Item {
    S w, r[3], n[3], fn, d[3], sj, p[3], u, q[3], iq[3], inv_mn, g, fo, dfn, inv_mnb;
  };
  std::vector<Item> items;
  bool on = false;
  S centre[3], mean_n[3], zlen, z[3], sec[9], tr, sq, arg, spread, num, den, gate, half_p, roll[9], spin[3],
      mean_u, om[3], iw[9], inv_m, tau;

  // items[j].w, r, n, fn set by the caller; on: whether the set is a line (dfn are zero if not)
  void forward(const S* om_in, const S* iw_in, S inv_m_in, S tau_in) {
    const int m = static_cast<int>(items.size());
    for (int i = 0; i < 3; ++i) om[i] = om_in[i];
    for (int i = 0; i < 9; ++i) iw[i] = iw_in[i];
    inv_m = inv_m_in;
    tau = tau_in;
    for (Item& it : items) it.dfn = 0;
    for (int i = 0; i < 3; ++i) centre[i] = mean_n[i] = 0;
    for (const Item& it : items)
      for (int i = 0; i < 3; ++i) {
        centre[i] += it.w * it.r[i];
        mean_n[i] += it.w * it.n[i];
      }
    zlen = std::sqrt(dot3(mean_n, mean_n) + S(TINY));
    for (int i = 0; i < 3; ++i) z[i] = mean_n[i] / zlen;
    for (int i = 0; i < 9; ++i) sec[i] = 0;
    for (Item& it : items) {
      for (int i = 0; i < 3; ++i) it.d[i] = it.r[i] - centre[i];
      it.sj = dot3(it.d, z);
      for (int i = 0; i < 3; ++i) it.p[i] = it.d[i] - it.sj * z[i];
      for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) sec[3 * i + k] += it.w * it.p[i] * it.p[k];
    }
    tr = sec[0] + sec[4] + sec[8];
    sq = 0;
    for (int i = 0; i < 9; ++i) sq += sec[i] * sec[i];
    arg = S(2) * sq - tr * tr;
    spread = std::sqrt(relu(arg) + S(TINY));
    num = tr + spread - S(schema::LINE_ASPECT) * (tr - spread);
    den = tr + spread + S(TINY);
    gate = relu(num / den);
    on = tr > S(schema::LINE_MIN_SPREAD) && gate > 0;
    if (!on || m == 0) return;
    half_p = S(0.5) * (S(1) + tr / spread);
    for (int i = 0; i < 3; ++i)
      for (int k = 0; k < 3; ++k)
        roll[3 * i + k] = half_p * (S(i == k ? 1 : 0) - z[i] * z[k]) - sec[3 * i + k] / spread;
    matvec(roll, om, spin);
    mean_u = 0;
    for (Item& it : items) {  // u = (spin x r) . n = spin . q, q = r x n
      cross3(it.r, it.n, it.q);
      it.u = dot3(spin, it.q);
      mean_u += it.w * it.u;
    }
    for (Item& it : items) {
      matvec(iw, it.q, it.iq);
      it.inv_mn = inv_m + dot3(it.q, it.iq);
      it.g = -(gate * it.w * (it.u - mean_u)) / (it.inv_mn * tau);
      it.fo = it.fn + it.g;
      it.dfn = relu(it.fo) - it.fn;
    }
  }

  // from dfnb (m), the cotangents of dfn, add to wb, rb (3 m), nb (3 m), fnb (m), omb (3), iwb (9)
  void backward(const S* dfnb, S* wb, S* rb, S* nb, S* fnb, S* omb, S* iwb) {
    if (!on) return;
    const int m = static_cast<int>(items.size());
    S gateb = 0, mean_ub = 0, spinb[3] = {0, 0, 0};
    std::vector<S>& yb = scratch<S>(11);
    yb.resize(m);
    for (int j = 0; j < m; ++j) {  // dfn = relu(fn + g) - fn, g = -gate w (u - mean_u) / (inv_mn tau)
      Item& it = items[j];
      const S gb = it.fo > 0 ? dfnb[j] : S(0);
      fnb[j] += gb - dfnb[j];
      const S y = it.u - mean_u, c = it.inv_mn * tau;
      gateb -= gb * it.w * y / c;
      wb[j] -= gb * gate * y / c;
      yb[j] = -gb * gate * it.w / c;
      it.inv_mnb = -gb * it.g / it.inv_mn;
      mean_ub -= yb[j];
    }
    std::vector<S>& db = scratch<S>(12);
    db.assign(3 * m, S(0));
    for (int j = 0; j < m; ++j) {  // mean_u = sum w u, u = spin . q; inv_mn = inv_m + q . iw q; q = r x n
      const Item& it = items[j];
      const S ub = yb[j] + mean_ub * it.w;
      wb[j] += mean_ub * it.u;
      S wtq[3], qb[3];
      matvec_t(iw, it.q, wtq);
      for (int i = 0; i < 3; ++i) {
        spinb[i] += ub * it.q[i];
        qb[i] = ub * spin[i] + it.inv_mnb * (it.iq[i] + wtq[i]);
      }
      for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) iwb[3 * i + k] += it.inv_mnb * it.q[i] * it.q[k];
      add_cross(it.n, qb, rb + 3 * j);
      add_cross(qb, it.r, nb + 3 * j);
    }
    // spin = roll om
    S rollb[9];
    for (int i = 0; i < 3; ++i)
      for (int k = 0; k < 3; ++k) rollb[3 * i + k] = spinb[i] * om[k];
    S rtb[3];
    matvec_t(roll, spinb, rtb);
    for (int i = 0; i < 3; ++i) omb[i] += rtb[i];
    // roll = half_p (I - z z^T) - sec / spread, half_p = (1 + tr / spread) / 2
    S half_pb = 0, zb[3] = {0, 0, 0}, secb[9], spreadb = 0, trb = 0;
    for (int i = 0; i < 3; ++i)
      for (int k = 0; k < 3; ++k) {
        const S rb_ik = rollb[3 * i + k];
        half_pb += rb_ik * (S(i == k ? 1 : 0) - z[i] * z[k]);
        zb[i] -= half_p * rb_ik * z[k];
        zb[k] -= half_p * rb_ik * z[i];
        secb[3 * i + k] = -rb_ik / spread;
        spreadb += rb_ik * sec[3 * i + k] / (spread * spread);
      }
    trb += S(0.5) * half_pb / spread;
    spreadb -= S(0.5) * half_pb * tr / (spread * spread);
    // gate = num / den (> 0 here), num = tr + spread - A (tr - spread), den = tr + spread + eps
    const S numb = gateb / den, denb = -gateb * gate / den;
    const S a = S(schema::LINE_ASPECT);
    trb += (S(1) - a) * numb + denb;
    spreadb += (S(1) + a) * numb + denb;
    // spread = sqrt(relu(2 sq - tr^2) + eps)
    if (arg > 0) {
      const S argb = spreadb / (S(2) * spread);
      const S sqb = S(2) * argb;
      trb -= S(2) * tr * argb;
      for (int i = 0; i < 9; ++i) secb[i] += S(2) * sqb * sec[i];
    }
    for (int i = 0; i < 3; ++i) secb[4 * i] += trb;
    // sec = sum w p p^T, p = d - (d . z) z, d = r - centre
    S centreb[3] = {0, 0, 0};
    for (int j = 0; j < m; ++j) {
      const Item& it = items[j];
      S sp[3], stp[3], pb[3];
      matvec(secb, it.p, sp);
      matvec_t(secb, it.p, stp);
      wb[j] += dot3(it.p, sp);
      for (int i = 0; i < 3; ++i) pb[i] = it.w * (sp[i] + stp[i]);
      S* dbj = &db[3 * j];
      const S sb = -dot3(pb, z);
      for (int i = 0; i < 3; ++i) {
        dbj[i] += pb[i] + sb * z[i];
        zb[i] += -it.sj * pb[i] + sb * it.d[i];
      }
      for (int i = 0; i < 3; ++i) {
        rb[3 * j + i] += dbj[i];
        centreb[i] -= dbj[i];
      }
    }
    // z = mean_n / sqrt(mean_n . mean_n + eps)
    S mean_nb[3];
    const S zm = dot3(zb, mean_n) / (zlen * zlen * zlen);
    for (int i = 0; i < 3; ++i) mean_nb[i] = zb[i] / zlen - mean_n[i] * zm;
    // centre = sum w r, mean_n = sum w n
    for (int j = 0; j < m; ++j) {
      const Item& it = items[j];
      wb[j] += dot3(mean_nb, it.n) + dot3(centreb, it.r);
      for (int i = 0; i < 3; ++i) {
        nb[3 * j + i] += it.w * mean_nb[i];
        rb[3 * j + i] += it.w * centreb[i];
      }
    }
  }
};

// ------------------------------------------------------------------ static contacts
// wrench W_s (6) of body a's picked static contacts (static_wrench in contacts.h) and its vjp
template <typename S>
struct StaticAdjoint {
  struct Contact {
    ContactLaw<S> law;
    int shape, sphere;
    int face;  // a static box's edge point (sphere < 0): the body's face it is nearest, and that side
    S sg;
    S r, c[3], p[3], d, gd[3], jn[9], arm[3];
    S pb[3], depthb;  // the way back
    S fnb, vtb[3], nb[3], armb[3], weightb;  // the way back, between its two passes
  };
  std::vector<Contact> contacts;
  S rot[9], inv_w[9], total, x[3], q[4], v[3], om[3];
  S tsum[3], alpha[3], acc[3];  // the set's normal torque, the accelerations it and its force give
  RollStick<S> roll;  // the roll stick of a line contact
  bool broken = false, empty = true;

  void forward(const World<S>& w, int a, const S* st, const std::vector<Pick>& picks, S* out) {
    for (int i = 0; i < 6; ++i) out[i] = S(0);
    broken = false;
    for (int i = 0; i < STATE_WIDTH && w.k > 0; ++i)
      if (std::isnan(st[i])) broken = true;
    if (broken) {  // as static_wrench: NaN wrench, no derivative
      for (int j = 0; j < 6; ++j) out[j] = std::numeric_limits<S>::quiet_NaN();
      return;
    }
    const int m = static_cast<int>(picks.size());
    contacts.resize(m);
    empty = m == 0;
    if (empty) return;
    for (int i = 0; i < 3; ++i) {
      x[i] = st[STATE_POSITION + i];
      v[i] = st[STATE_LINEAR_VELOCITY + i];
      om[i] = st[STATE_ANGULAR_VELOCITY + i];
    }
    for (int i = 0; i < 4; ++i) q[i] = st[STATE_ORIENTATION + i];
    quat_to_matrix(q, rot);
    rotate_tensor(rot, w.inv_inertia + 9 * a, inv_w);
    total = 0;
    using D3 = Dual<S, 3>;
    for (int j = 0; j < m; ++j) {
      Contact& ct = contacts[j];
      ct.shape = picks[j].shape;
      ct.sphere = picks[j].sphere;
      if (ct.sphere < 0) {  // a static box's edge point against the box body's face (edge_contact)
        S P[3], l[3];
        edge_point(w.shapes[ct.shape], -1 - ct.sphere, P);
        edge_contact<S, S>(P, x, rot, w.box_half + 3 * a, ct.law.depth, ct.law.n, ct.arm, &ct.face, l);
        ct.sg = l[ct.face] < 0 ? S(-1) : S(1);
        total += ct.law.depth;
        continue;
      }
      ct.r = static_point(w, a, corner_contacts(w, a, ct.shape), ct.sphere, ct.c);
      sphere_center(x, rot, ct.c, ct.p);
      D3 p3[3], d3, n3[3];
      for (int i = 0; i < 3; ++i) {
        p3[i] = D3(ct.p[i]);
        p3[i].d[i] = S(1);
      }
      distance_direct<D3, S>(w.shapes[ct.shape], p3, d3, n3);
      ct.d = d3.v;
      ContactLaw<S>& law = ct.law;
      for (int i = 0; i < 3; ++i) {
        ct.gd[i] = d3.d[i];
        law.n[i] = n3[i].v;
        for (int k = 0; k < 3; ++k) ct.jn[3 * i + k] = n3[i].d[k];
      }
      law.depth = relu(ct.r - ct.d);
      for (int i = 0; i < 3; ++i) ct.arm[i] = (ct.p[i] - x[i]) - law.n[i] * ct.r;
      total += law.depth;
    }
    const S tiny = std::numeric_limits<S>::min();
    const S mass = w.mass[a];
    S fsum[3] = {0, 0, 0};  // the set's normal wrench, summed in pick order as static_wrench
    for (int i = 0; i < 3; ++i) tsum[i] = 0;
    for (int j = 0; j < m; ++j) {
      Contact& ct = contacts[j];
      ContactLaw<S>& law = ct.law;
      law.arms = 1;
      law.weight = law.depth / (total + tiny);
      S wr[3];
      cross3(om, ct.arm, wr);
      for (int i = 0; i < 3; ++i) law.vel[i] = v[i] + wr[i];
      law.stiff = mass * w.omega * w.omega;
      law.unload = w.unload_static[a * w.k + ct.shape];
      law.mu = w.mu_static[a * w.k + ct.shape];
      law.inv_m = S(1) / mass;
      law.h = w.h;
      law.unload_velocity = w.unload_velocity;
      law.arm[0] = ct.arm;
      law.inv_w[0] = inv_w;
      law.inv_i_min[0] = w.inv_i_min[a];
      law.forward_normal();
      S f[3], tq[3];
      for (int i = 0; i < 3; ++i) f[i] = law.fn * law.n[i];
      cross3(ct.arm, f, tq);
      for (int i = 0; i < 3; ++i) {
        fsum[i] += f[i];
        tsum[i] += tq[i];
      }
    }
    // the accelerations the set's normal wrench gives, the predicted slips, the friction
    const S inv_m = S(1) / mass;
    for (int i = 0; i < 3; ++i) acc[i] = fsum[i] * inv_m;
    matvec(inv_w, tsum, alpha);
    for (int j = 0; j < m; ++j) {
      Contact& ct = contacts[j];
      ContactLaw<S>& law = ct.law;
      S dv[3];
      cross3(alpha, ct.arm, dv);
      for (int i = 0; i < 3; ++i) dv[i] += acc[i];
      law.predict(dv, w.h);
      law.forward_friction();
      S tq[3];
      cross3(ct.arm, law.f, tq);
      for (int i = 0; i < 3; ++i) {
        out[i] += law.f[i];
        out[3 + i] += tq[i];
      }
    }
    roll.items.resize(m);
    for (int j = 0; j < m; ++j) {
      const Contact& ct = contacts[j];
      typename RollStick<S>::Item& it = roll.items[j];
      it.w = ct.law.weight;
      it.fn = ct.law.fn;
      for (int i = 0; i < 3; ++i) {
        it.r[i] = ct.arm[i];
        it.n[i] = ct.law.n[i];
      }
    }
    if (is_box_body(w, a))  // no roll stick on a box's corners (contacts.h, static_wrench)
      roll.on = false;
    else
      roll.forward(om, inv_w, inv_m, roll_stop_time(w));
    if (roll.on)
      for (int j = 0; j < m; ++j) {
        const Contact& ct = contacts[j];
        S f[3], tq[3];
        for (int i = 0; i < 3; ++i) f[i] = roll.items[j].dfn * ct.law.n[i];
        cross3(ct.arm, f, tq);
        for (int i = 0; i < 3; ++i) {
          out[i] += f[i];
          out[3 + i] += tq[i];
        }
      }
  }

  // gs (STATE_WIDTH) += (d W_s / d st)^T mu, mu (6) the wrench's cotangent
  void backward(const World<S>& w, int a, const S* mu, S* gs) {
    if (broken || empty) return;
    const S tiny = std::numeric_limits<S>::min();
    S xb[3] = {0, 0, 0}, rb[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, vb[3] = {0, 0, 0}, omb[3] = {0, 0, 0};
    S iwb[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    S totalb = 0;
    const S* mf = mu;
    const S* mt = mu + 3;
    const S h = w.h;
    S accb[3] = {0, 0, 0}, alphab[3] = {0, 0, 0};
    for (Contact& ct : contacts) {  // the friction's part, and the predicted slip's
      const ContactLaw<S>& law = ct.law;
      // W += (f, arm x f)
      S fb[3] = {mf[0], mf[1], mf[2]};
      add_cross(mt, ct.arm, fb);
      for (int i = 0; i < 3; ++i) ct.armb[i] = ct.nb[i] = 0;
      add_cross(law.f, mt, ct.armb);
      S* armbs[1] = {ct.armb};
      S* iwbs[1] = {iwb};
      law.backward_friction(fb, ct.nb, armbs, iwbs, ct.fnb, ct.vtb, ct.weightb);
      // vs = vt + pred, dv = acc + alpha x arm
      S dvb[3];
      law.predict_backward(ct.vtb, h, dvb, ct.nb);
      for (int i = 0; i < 3; ++i) accb[i] += dvb[i];
      add_cross(ct.arm, dvb, alphab);
      add_cross(dvb, alpha, ct.armb);
    }
    if (roll.on) {  // the roll stick's force dfn n on each contact, and its torque arm x dfn n
      const int m = static_cast<int>(contacts.size());
      std::vector<S>& buf = scratch<S>(13);  // dfnb, wb, fnb (m each), rb, nb (3 m each)
      buf.assign(9 * m, S(0));
      S* dfnb = buf.data();
      S* wb = dfnb + m;
      S* fnb = wb + m;
      S* rb = fnb + m;
      S* nb = rb + 3 * m;
      for (int j = 0; j < m; ++j) {
        Contact& ct = contacts[j];
        const S dfn = roll.items[j].dfn;
        S fb[3] = {mf[0], mf[1], mf[2]}, f[3];
        add_cross(mt, ct.arm, fb);
        for (int i = 0; i < 3; ++i) f[i] = dfn * ct.law.n[i];
        dfnb[j] = dot3(fb, ct.law.n);
        for (int i = 0; i < 3; ++i) ct.nb[i] += dfn * fb[i];
        add_cross(f, mt, ct.armb);
      }
      roll.backward(dfnb, wb, rb, nb, fnb, omb, iwb);
      for (int j = 0; j < m; ++j) {
        Contact& ct = contacts[j];
        ct.fnb += fnb[j];
        ct.weightb += wb[j];
        for (int i = 0; i < 3; ++i) {
          ct.armb[i] += rb[3 * j + i];
          ct.nb[i] += nb[3 * j + i];
        }
      }
    }
    // acc = F / m, alpha = inv_w T
    const S inv_m = S(1) / w.mass[a];
    S fsb[3], tsb[3];
    for (int i = 0; i < 3; ++i) fsb[i] = accb[i] * inv_m;
    matvec_t(inv_w, alphab, tsb);
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) iwb[3 * i + j] += alphab[i] * tsum[j];
    for (Contact& ct : contacts) {  // F = sum fn n, T = sum arm x fn n; then the normal force's part
      const ContactLaw<S>& law = ct.law;
      S yb[3], y[3];
      for (int i = 0; i < 3; ++i) {
        yb[i] = fsb[i];
        y[i] = law.fn * law.n[i];
      }
      add_cross(tsb, ct.arm, yb);
      add_cross(y, tsb, ct.armb);
      S* nb = ct.nb;
      S* armb = ct.armb;
      S velb[3] = {0, 0, 0};
      S depthb;
      S weightb = ct.weightb;
      law.backward_normal_and_sum(ct.fnb, yb, ct.vtb, nb, velb, depthb, weightb);
      // vel = v + om x arm
      for (int i = 0; i < 3; ++i) vb[i] += velb[i];
      add_cross(ct.arm, velb, omb);
      add_cross(velb, om, armb);
      // weight = depth / (total + tiny)
      const S tt = total + tiny;
      depthb += weightb / tt;
      totalb -= weightb * law.depth / (tt * tt);
      ct.depthb = depthb;
      if (ct.sphere < 0) {  // arm = P - x, n = -sg R e_face
        for (int i = 0; i < 3; ++i) {
          xb[i] -= armb[i];
          rb[3 * i + ct.face] -= ct.sg * nb[i];
        }
        continue;
      }
      // arm = (p - x) - n r
      for (int i = 0; i < 3; ++i) {
        ct.pb[i] = armb[i];
        xb[i] -= armb[i];
        nb[i] -= ct.r * armb[i];
      }
      for (int k = 0; k < 3; ++k) ct.pb[k] += nb[0] * ct.jn[k] + nb[1] * ct.jn[3 + k] + nb[2] * ct.jn[6 + k];
    }
    for (Contact& ct : contacts) {
      const S depthb = ct.depthb + totalb;
      if (ct.sphere < 0) {  // depth = half_f - |l_f|, l = R^T (P - x), P - x = arm
        const S lb = -ct.sg * depthb;
        for (int i = 0; i < 3; ++i) {
          rb[3 * i + ct.face] += lb * ct.arm[i];
          xb[i] -= lb * rot[3 * i + ct.face];
        }
        continue;
      }
      if (ct.r - ct.d > 0)  // depth = relu(r - d)
        for (int i = 0; i < 3; ++i) ct.pb[i] -= depthb * ct.gd[i];
      // p = x + R c
      for (int i = 0; i < 3; ++i) {
        xb[i] += ct.pb[i];
        for (int k = 0; k < 3; ++k) rb[3 * i + k] += ct.pb[i] * ct.c[k];
      }
    }
    rotate_tensor_vjp(rot, w.inv_inertia + 9 * a, iwb, rb);
    S qb[4] = {0, 0, 0, 0};
    quat_to_matrix_vjp(q, rb, qb);
    for (int i = 0; i < 3; ++i) {
      gs[STATE_POSITION + i] += xb[i];
      gs[STATE_LINEAR_VELOCITY + i] += vb[i];
      gs[STATE_ANGULAR_VELOCITY + i] += omb[i];
    }
    for (int i = 0; i < 4; ++i) gs[STATE_ORIENTATION + i] += qb[i];
  }
};

// ------------------------------------------------------------------ body pairs
// wrench (12: on a, then on b) of pair pi's picked sphere pairs (pair_wrench in contacts.h) and
// its vjp
template <typename S>
struct PairAdjoint {
  struct Contact {
    ContactLaw<S> law;
    S ca[3], cb[3], r_a, diff[3], dist, arm_a[3], arm_b[3];
    int box = 0;           // 1: b's box surface (cb its clamped point), 2: a's (ca), 0: spheres
    S rel[3], free[3];     // the sphere's centre from the box's centre; box_partner's free
    S pab[3], pbb[3], depthb;
    S fnb, vtb[3], nb[3], armab[3], armbb[3], weightb;  // between the two passes back
  };
  std::vector<Contact> contacts;
  S rot_a[9], rot_b[9], iw_a[9], iw_b[9], total;
  S tsa[3], tsb[3], alpha_a[3], alpha_b[3], inv_m = 0;
  int a = 0, b = 0;

  void forward(const World<S>& w, int pi, const S* st_a, const S* st_b, const std::vector<PairPick>& picks,
               S* out) {
    for (int i = 0; i < 12; ++i) out[i] = S(0);
    const int m = static_cast<int>(picks.size());
    contacts.resize(m);
    if (m == 0) return;
    a = static_cast<int>(w.pairs[2 * pi]);
    b = static_cast<int>(w.pairs[2 * pi + 1]);
    quat_to_matrix(st_a + STATE_ORIENTATION, rot_a);
    quat_to_matrix(st_b + STATE_ORIENTATION, rot_b);
    rotate_tensor(rot_a, w.inv_inertia + 9 * a, iw_a);
    rotate_tensor(rot_b, w.inv_inertia + 9 * b, iw_b);
    total = 0;
    for (int k = 0; k < m; ++k) {
      Contact& ct = contacts[k];
      S pa[3], pb[3];
      ct.r_a = 0;
      S r_b = 0;
      ct.box = picks[k].j < 0 ? 1 : (picks[k].i < 0 ? 2 : 0);
      if (picks[k].i >= 0) {
        const S* ca = w.centers + (static_cast<int64_t>(a) * w.s_max + picks[k].i) * 3;
        for (int i = 0; i < 3; ++i) ct.ca[i] = ca[i];
        ct.r_a = w.radii[a * w.s_max + picks[k].i];
        sphere_center(st_a + STATE_POSITION, rot_a, ca, pa);
      }
      if (picks[k].j >= 0) {
        const S* cb = w.centers + (static_cast<int64_t>(b) * w.s_max + picks[k].j) * 3;
        for (int i = 0; i < 3; ++i) ct.cb[i] = cb[i];
        r_b = w.radii[b * w.s_max + picks[k].j];
        sphere_center(st_b + STATE_POSITION, rot_b, cb, pb);
      }
      if (ct.box != 0) {  // the box's surface as the other's sphere's partner (box_partner)
        const bool on_b = ct.box == 1;
        const S* xbox = (on_b ? st_b : st_a) + STATE_POSITION;
        const S* rbox = on_b ? rot_b : rot_a;
        const S* half = w.box_half + 3 * (on_b ? b : a);
        const S* p = on_b ? pa : pb;
        S* cl = on_b ? ct.cb : ct.ca;
        box_partner(xbox, rbox, half, p, cl, on_b ? pb : pa, ct.free, on_b ? r_b : ct.r_a);
        for (int i = 0; i < 3; ++i) ct.rel[i] = p[i] - xbox[i];
      }
      for (int i = 0; i < 3; ++i) ct.diff[i] = pb[i] - pa[i];
      ct.dist = std::sqrt(dot3(ct.diff, ct.diff) + S(NORMAL_EPS2));
      ContactLaw<S>& law = ct.law;
      for (int i = 0; i < 3; ++i) law.n[i] = ct.diff[i] / ct.dist;
      law.depth = relu((ct.r_a + r_b) - ct.dist);
      for (int i = 0; i < 3; ++i) {
        const S point = pa[i] + law.n[i] * ct.r_a;
        ct.arm_a[i] = point - st_a[STATE_POSITION + i];
        ct.arm_b[i] = point - st_b[STATE_POSITION + i];
      }
      total += law.depth;
    }
    const S tiny = std::numeric_limits<S>::min();
    S fsum[3] = {0, 0, 0}, acc[3];  // the pair's normal force (on b) and torques, in pick order
    for (int i = 0; i < 3; ++i) tsa[i] = tsb[i] = 0;
    for (int k = 0; k < m; ++k) {
      Contact& ct = contacts[k];
      ContactLaw<S>& law = ct.law;
      law.arms = 2;
      law.weight = law.depth / (total + tiny);
      S wa[3], wb[3];
      cross3(st_a + STATE_ANGULAR_VELOCITY, ct.arm_a, wa);
      cross3(st_b + STATE_ANGULAR_VELOCITY, ct.arm_b, wb);
      for (int i = 0; i < 3; ++i)
        law.vel[i] = (st_b[STATE_LINEAR_VELOCITY + i] + wb[i]) - (st_a[STATE_LINEAR_VELOCITY + i] + wa[i]);
      law.stiff = w.mass_pair[pi] * w.omega * w.omega;
      law.unload = w.unload_pair[pi];
      law.mu = w.mu_pair[pi];
      law.inv_m = S(1) / w.mass[a] + S(1) / w.mass[b];
      law.h = w.h;
      law.unload_velocity = w.unload_velocity;
      law.arm[0] = ct.arm_a;
      law.arm[1] = ct.arm_b;
      law.inv_w[0] = iw_a;
      law.inv_w[1] = iw_b;
      law.inv_i_min[0] = w.inv_i_min[a];
      law.inv_i_min[1] = w.inv_i_min[b];
      law.forward_normal();
      S f[3], neg[3], ta[3], tb[3];
      for (int i = 0; i < 3; ++i) {
        f[i] = law.fn * law.n[i];
        neg[i] = -f[i];
      }
      cross3(ct.arm_a, neg, ta);
      cross3(ct.arm_b, f, tb);
      for (int i = 0; i < 3; ++i) {
        fsum[i] += f[i];
        tsa[i] += ta[i];
        tsb[i] += tb[i];
      }
    }
    // the relative acceleration the pair's normal forces give, the predicted slips, the friction
    inv_m = S(1) / w.mass[a] + S(1) / w.mass[b];
    for (int i = 0; i < 3; ++i) acc[i] = fsum[i] * inv_m;
    matvec(iw_a, tsa, alpha_a);
    matvec(iw_b, tsb, alpha_b);
    for (int k = 0; k < m; ++k) {
      Contact& ct = contacts[k];
      ContactLaw<S>& law = ct.law;
      S dva[3], dvb[3], dv[3];
      cross3(alpha_a, ct.arm_a, dva);
      cross3(alpha_b, ct.arm_b, dvb);
      for (int i = 0; i < 3; ++i) dv[i] = acc[i] + dvb[i] - dva[i];
      law.predict(dv, w.h);
      law.forward_friction();
      const S* f = law.f;
      S neg[3] = {-f[0], -f[1], -f[2]}, ta[3], tb[3];
      cross3(ct.arm_a, neg, ta);
      cross3(ct.arm_b, f, tb);
      for (int i = 0; i < 3; ++i) {
        out[i] -= f[i];
        out[3 + i] += ta[i];
        out[6 + i] += f[i];
        out[9 + i] += tb[i];
      }
    }
  }

  // ga, gb (STATE_WIDTH each) += (d W_p / d (st_a, st_b))^T mu, mu (12) the cotangent of (wrench on a, on b)
  void backward(const World<S>& w, const S* st_a, const S* st_b, const S* mu, S* ga, S* gb) {
    if (contacts.empty()) return;
    const S tiny = std::numeric_limits<S>::min();
    S xab[3] = {0, 0, 0}, xbb[3] = {0, 0, 0}, vab[3] = {0, 0, 0}, vbb[3] = {0, 0, 0};
    S omab[3] = {0, 0, 0}, ombb[3] = {0, 0, 0};
    S rab[9] = {}, rbb[9] = {}, iwab[9] = {}, iwbb[9] = {};
    S totalb = 0;
    const S *mfa = mu, *mta = mu + 3, *mfb = mu + 6, *mtb = mu + 9;
    const S* om_a = st_a + STATE_ANGULAR_VELOCITY;
    const S* om_b = st_b + STATE_ANGULAR_VELOCITY;
    const S h = w.h;
    S accb[3] = {0, 0, 0}, alphaab[3] = {0, 0, 0}, alphabb[3] = {0, 0, 0};
    for (Contact& ct : contacts) {  // the friction's part, and the predicted slip's
      const ContactLaw<S>& law = ct.law;
      const S* f = law.f;
      // on a: (-f, arm_a x -f); on b: (f, arm_b x f)
      S fb[3];
      for (int i = 0; i < 3; ++i) fb[i] = mfb[i] - mfa[i];
      for (int i = 0; i < 3; ++i) ct.armab[i] = ct.armbb[i] = ct.nb[i] = 0;
      S tmp[3] = {0, 0, 0};
      add_cross(mta, ct.arm_a, tmp);
      for (int i = 0; i < 3; ++i) fb[i] -= tmp[i];
      add_cross(mtb, ct.arm_b, fb);
      S negf[3] = {-f[0], -f[1], -f[2]};
      add_cross(negf, mta, ct.armab);
      add_cross(f, mtb, ct.armbb);
      S* armbs[2] = {ct.armab, ct.armbb};
      S* iwbs[2] = {iwab, iwbb};
      law.backward_friction(fb, ct.nb, armbs, iwbs, ct.fnb, ct.vtb, ct.weightb);
      // vs = vt + pred, dv = acc + alpha_b x arm_b - alpha_a x arm_a
      S dvb[3], ndvb[3];
      law.predict_backward(ct.vtb, h, dvb, ct.nb);
      for (int i = 0; i < 3; ++i) {
        ndvb[i] = -dvb[i];
        accb[i] += dvb[i];
      }
      add_cross(ct.arm_b, dvb, alphabb);
      add_cross(dvb, alpha_b, ct.armbb);
      add_cross(ct.arm_a, ndvb, alphaab);
      add_cross(ndvb, alpha_a, ct.armab);
    }
    // acc = F inv_m, alpha_a = iw_a T_a, alpha_b = iw_b T_b
    S fsb[3], tsab[3], tsbb[3];
    for (int i = 0; i < 3; ++i) fsb[i] = accb[i] * inv_m;
    matvec_t(iw_a, alphaab, tsab);
    matvec_t(iw_b, alphabb, tsbb);
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        iwab[3 * i + j] += alphaab[i] * tsa[j];
        iwbb[3 * i + j] += alphabb[i] * tsb[j];
      }
    for (Contact& ct : contacts) {  // F = sum y, T_b = sum arm_b x y, T_a = sum arm_a x -y (y = fn n)
      const ContactLaw<S>& law = ct.law;
      S y[3], ny[3], yb[3], zb[3] = {0, 0, 0};
      for (int i = 0; i < 3; ++i) {
        y[i] = law.fn * law.n[i];
        ny[i] = -y[i];
        yb[i] = fsb[i];
      }
      add_cross(tsbb, ct.arm_b, yb);
      add_cross(y, tsbb, ct.armbb);
      add_cross(tsab, ct.arm_a, zb);
      add_cross(ny, tsab, ct.armab);
      for (int i = 0; i < 3; ++i) yb[i] -= zb[i];
      S* nb = ct.nb;
      S* armab = ct.armab;
      S* armbb = ct.armbb;
      S velb[3] = {0, 0, 0};
      S depthb;
      S weightb = ct.weightb;
      law.backward_normal_and_sum(ct.fnb, yb, ct.vtb, nb, velb, depthb, weightb);
      // vel = (v_b + om_b x arm_b) - (v_a + om_a x arm_a)
      for (int i = 0; i < 3; ++i) {
        vbb[i] += velb[i];
        vab[i] -= velb[i];
      }
      add_cross(ct.arm_b, velb, ombb);
      add_cross(velb, om_b, armbb);
      S nvelb[3] = {-velb[0], -velb[1], -velb[2]};
      add_cross(ct.arm_a, nvelb, omab);
      add_cross(nvelb, om_a, armab);
      const S tt = total + tiny;
      depthb += weightb / tt;
      totalb -= weightb * law.depth / (tt * tt);
      // arm_a = point - x_a, arm_b = point - x_b, point = p_a + n r_a
      for (int i = 0; i < 3; ++i) {
        const S pointb = armab[i] + armbb[i];
        xab[i] -= armab[i];
        xbb[i] -= armbb[i];
        ct.pab[i] = pointb;
        ct.pbb[i] = 0;
        nb[i] += ct.r_a * pointb;
      }
      // n = diff / dist (dist's own dependence on diff: below, with the depth's)
      const S ndot = dot3(nb, ct.diff) / (ct.dist * ct.dist);
      S diffb[3];
      for (int i = 0; i < 3; ++i) diffb[i] = nb[i] / ct.dist;
      ct.depthb = depthb;
      // keep dist's cotangent from n in depthb's place: distb = -ndot - depthb (relu active)
      for (int i = 0; i < 3; ++i) {
        diffb[i] -= ndot * ct.diff[i] / ct.dist;
        ct.pbb[i] += diffb[i];
        ct.pab[i] -= diffb[i];
      }
    }
    for (Contact& ct : contacts) {
      const S depthb = ct.depthb + totalb;
      if (ct.law.depth > 0) {  // depth = relu(r_a + r_b - dist), dist = sqrt(diff.diff + NORMAL_EPS2)
        for (int i = 0; i < 3; ++i) {
          const S diffb = -depthb * ct.diff[i] / ct.dist;
          ct.pbb[i] += diffb;
          ct.pab[i] -= diffb;
        }
      }
      if (ct.box != 0) {  // the box's point x + R cl (box_partner): the part through cl's free components
        const bool on_b = ct.box == 1;
        const S* rbox = on_b ? rot_b : rot_a;
        const S* qb = on_b ? ct.pbb : ct.pab;  // the box point's cotangent
        S* pother = on_b ? ct.pab : ct.pbb;    // the sphere centre's
        S* xbox = on_b ? xbb : xab;
        S* rb_ = on_b ? rbb : rab;
        S lb[3], u[3];
        for (int j = 0; j < 3; ++j) lb[j] = ct.free[j] * (rbox[j] * qb[0] + rbox[3 + j] * qb[1] + rbox[6 + j] * qb[2]);
        for (int i = 0; i < 3; ++i) u[i] = rbox[3 * i] * lb[0] + rbox[3 * i + 1] * lb[1] + rbox[3 * i + 2] * lb[2];
        for (int i = 0; i < 3; ++i) {
          pother[i] += u[i];
          xbox[i] -= u[i];
          for (int k = 0; k < 3; ++k) rb_[3 * i + k] += ct.rel[i] * lb[k];
        }
      }
      // p_a = x_a + R_a c_a, p_b = x_b + R_b c_b (c a box's cl)
      for (int i = 0; i < 3; ++i) {
        xab[i] += ct.pab[i];
        xbb[i] += ct.pbb[i];
        for (int k = 0; k < 3; ++k) {
          rab[3 * i + k] += ct.pab[i] * ct.ca[k];
          rbb[3 * i + k] += ct.pbb[i] * ct.cb[k];
        }
      }
    }
    rotate_tensor_vjp(rot_a, w.inv_inertia + 9 * a, iwab, rab);
    rotate_tensor_vjp(rot_b, w.inv_inertia + 9 * b, iwbb, rbb);
    S qab[4] = {0, 0, 0, 0}, qbb[4] = {0, 0, 0, 0};
    quat_to_matrix_vjp(st_a + STATE_ORIENTATION, rab, qab);
    quat_to_matrix_vjp(st_b + STATE_ORIENTATION, rbb, qbb);
    for (int i = 0; i < 3; ++i) {
      ga[STATE_POSITION + i] += xab[i];
      gb[STATE_POSITION + i] += xbb[i];
      ga[STATE_LINEAR_VELOCITY + i] += vab[i];
      gb[STATE_LINEAR_VELOCITY + i] += vbb[i];
      ga[STATE_ANGULAR_VELOCITY + i] += omab[i];
      gb[STATE_ANGULAR_VELOCITY + i] += ombb[i];
    }
    for (int i = 0; i < 4; ++i) {
      ga[STATE_ORIENTATION + i] += qab[i];
      gb[STATE_ORIENTATION + i] += qbb[i];
    }
  }
};

// ------------------------------------------------------------------ integration
// s' = I(s, W) of integrate.h: gs (STATE_WIDTH) += (d s' / d s)^T lam, wb (6) = (d s' / d W)^T lam
template <typename S>
void integrate_vjp(const World<S>& w, int a, const S* st, const S* wr, const S* lam, S* gs, S* wb) {
  const S* q = st + STATE_ORIENTATION;
  const S* om0 = st + STATE_ANGULAR_VELOCITY;
  S rot[9];
  quat_to_matrix(q, rot);
  const S hm = w.h / w.mass[a];
  const S* inertia = w.inertia + 9 * a;
  const S* inv_inertia = w.inv_inertia + 9 * a;
  // forward
  S body[3], tmp[3], lw[3], gyro[3], rhs[3], body2[3], tmp2[3], acc[3], om[3];
  matvec_t(rot, om0, body);
  matvec(inertia, body, tmp);
  matvec(rot, tmp, lw);
  cross3(om0, lw, gyro);
  for (int i = 0; i < 3; ++i) rhs[i] = wr[3 + i] - gyro[i];
  matvec_t(rot, rhs, body2);
  matvec(inv_inertia, body2, tmp2);
  matvec(rot, tmp2, acc);
  for (int i = 0; i < 3; ++i) om[i] = om0[i] + w.h * acc[i];
  S r[3] = {om[0] * w.h, om[1] * w.h, om[2] * w.h};
  const S eps = sizeof(S) == 8 ? S(schema::SMALL_ANGLE_F64) : S(schema::SMALL_ANGLE_F32);
  const S sq = dot3(r, r);
  const bool small = sq < eps * eps;
  S sinc, co, norm = 0, half = 0, sh = 0, ch = 0;
  if (small) {
    sinc = 0.5 - sq / S(48);
    co = 1.0 - sq / S(8);
  } else {
    norm = std::sqrt(sq);
    half = 0.5 * norm;
    sh = std::sin(half);
    ch = std::cos(half);
    sinc = sh / norm;
    co = ch;
  }
  const S e[4] = {co, sinc * r[0], sinc * r[1], sinc * r[2]};
  S qn[4];
  qn[0] = e[0] * q[0] - e[1] * q[1] - e[2] * q[2] - e[3] * q[3];
  qn[1] = e[0] * q[1] + e[1] * q[0] + e[2] * q[3] - e[3] * q[2];
  qn[2] = e[0] * q[2] - e[1] * q[3] + e[2] * q[0] + e[3] * q[1];
  qn[3] = e[0] * q[3] + e[1] * q[2] - e[2] * q[1] + e[3] * q[0];
  const S len = std::sqrt(qn[0] * qn[0] + qn[1] * qn[1] + qn[2] * qn[2] + qn[3] * qn[3]);
  S qo[4];
  for (int i = 0; i < 4; ++i) qo[i] = qn[i] / len;
  // back: out x = x + h v', v' = v + hm F, out q = qn / |qn|, out om = om
  const S* lx = lam + STATE_POSITION;
  const S* lq = lam + STATE_ORIENTATION;
  const S* lv = lam + STATE_LINEAR_VELOCITY;
  const S* lo = lam + STATE_ANGULAR_VELOCITY;
  S vnb[3];
  for (int i = 0; i < 3; ++i) {
    gs[STATE_POSITION + i] += lx[i];
    vnb[i] = lv[i] + w.h * lx[i];
    gs[STATE_LINEAR_VELOCITY + i] += vnb[i];
    wb[i] = hm * vnb[i];
  }
  const S qdot = qo[0] * lq[0] + qo[1] * lq[1] + qo[2] * lq[2] + qo[3] * lq[3];
  S qnb[4];
  for (int i = 0; i < 4; ++i) qnb[i] = (lq[i] - qo[i] * qdot) / len;
  S eb[4];
  eb[0] = qnb[0] * q[0] + qnb[1] * q[1] + qnb[2] * q[2] + qnb[3] * q[3];
  eb[1] = -qnb[0] * q[1] + qnb[1] * q[0] - qnb[2] * q[3] + qnb[3] * q[2];
  eb[2] = -qnb[0] * q[2] + qnb[1] * q[3] + qnb[2] * q[0] - qnb[3] * q[1];
  eb[3] = -qnb[0] * q[3] - qnb[1] * q[2] + qnb[2] * q[1] + qnb[3] * q[0];
  S qb[4];
  qb[0] = qnb[0] * e[0] + qnb[1] * e[1] + qnb[2] * e[2] + qnb[3] * e[3];
  qb[1] = -qnb[0] * e[1] + qnb[1] * e[0] + qnb[2] * e[3] - qnb[3] * e[2];
  qb[2] = -qnb[0] * e[2] - qnb[1] * e[3] + qnb[2] * e[0] + qnb[3] * e[1];
  qb[3] = -qnb[0] * e[3] + qnb[1] * e[2] - qnb[2] * e[1] + qnb[3] * e[0];
  // e = (co, sinc r)
  const S cob = eb[0];
  const S sincb = eb[1] * r[0] + eb[2] * r[1] + eb[3] * r[2];
  S rb[3] = {sinc * eb[1], sinc * eb[2], sinc * eb[3]};
  S sqb;
  if (small) {
    sqb = -sincb / S(48) - cob / S(8);
  } else {
    const S normb = sincb * (ch * S(0.5) * norm - sh) / (norm * norm) - cob * sh * S(0.5);
    sqb = normb * S(0.5) / norm;
  }
  for (int i = 0; i < 3; ++i) rb[i] += S(2) * sqb * r[i];
  // om = om0 + h acc, r = h om
  S omb[3], accb[3];
  for (int i = 0; i < 3; ++i) {
    omb[i] = lo[i] + w.h * rb[i];
    accb[i] = w.h * omb[i];
  }
  S om0b[3] = {omb[0], omb[1], omb[2]};
  S rotb[9] = {};
  // acc = R tmp2, tmp2 = Iinv body2, body2 = R^T rhs
  S tmp2b[3], body2b[3], rhsb[3];
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) rotb[3 * i + k] += accb[i] * tmp2[k];
  matvec_t(rot, accb, tmp2b);
  matvec_t(inv_inertia, tmp2b, body2b);
  matvec(rot, body2b, rhsb);
  for (int j = 0; j < 3; ++j)
    for (int i = 0; i < 3; ++i) rotb[3 * j + i] += rhs[j] * body2b[i];
  // rhs = tau - gyro, gyro = om0 x lw
  for (int i = 0; i < 3; ++i) wb[3 + i] = rhsb[i];
  S gyrob[3] = {-rhsb[0], -rhsb[1], -rhsb[2]};
  S lwb[3] = {0, 0, 0};
  add_cross(lw, gyrob, om0b);
  add_cross(gyrob, om0, lwb);
  // lw = R tmp, tmp = I body, body = R^T om0
  S tmpb[3], bodyb[3], viab[3];
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) rotb[3 * i + k] += lwb[i] * tmp[k];
  matvec_t(rot, lwb, tmpb);
  matvec_t(inertia, tmpb, bodyb);
  matvec(rot, bodyb, viab);
  for (int i = 0; i < 3; ++i) om0b[i] += viab[i];
  for (int j = 0; j < 3; ++j)
    for (int i = 0; i < 3; ++i) rotb[3 * j + i] += om0[j] * bodyb[i];
  quat_to_matrix_vjp(q, rotb, qb);
  for (int i = 0; i < 4; ++i) gs[STATE_ORIENTATION + i] += qb[i];
  for (int i = 0; i < 3; ++i) gs[STATE_ANGULAR_VELOCITY + i] += om0b[i];
}

}  // namespace dv
