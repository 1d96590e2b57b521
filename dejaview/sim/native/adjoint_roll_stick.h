// Reverse mode by hand (adjoint.h): the roll stick of a line contact (static_contacts.h's
// line_roll_stick; dejaview/sim/line_contact.py).
#pragma once

#include <cmath>
#include <vector>

#include "adjoint_law.h"

namespace dv {

// ------------------------------------------------------------------ the roll stick of a line contact
// static_contacts.h's line_roll_stick on values, with what the way back needs, and its vjp. Inputs per
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

}  // namespace dv
