// Reverse mode by hand (adjoint.h): the wrenches of a body pair's contacts (pair_wrench).
#pragma once

#include <cmath>
#include <limits>
#include <vector>

#include "adjoint_law.h"

namespace dv {

// ------------------------------------------------------------------ body pairs
// wrench (12: on a, then on b) of pair pi's picked sphere pairs (pair_wrench in pair_contacts.h)
// and its vjp
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
      law.stiff = contact_stiffness(w, w.mass_pair[pi]);
      law.unload = scaled_unload(w, w.unload_pair[pi]);
      law.mu = scaled_mu(w, w.mu_pair[pi]);
      law.inv_m = S(1) / w.mass[a] + S(1) / w.mass[b];
      law.h = w.h;
      law.unload_velocity = w.unload_velocity;
      law.omega = w.omega;
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
  void backward(const World<S>& w, const S* st_a, const S* st_b, const S* mu, S* ga, S* gb, S* gp) {
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
      law.add_material_gradient(gp);
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

}  // namespace dv
