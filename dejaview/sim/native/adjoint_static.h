// Reverse mode by hand (adjoint.h): the wrench of a body's static contacts (static_wrench).
#pragma once

#include <cmath>
#include <limits>
#include <vector>

#include "adjoint_roll_stick.h"

namespace dv {

// ------------------------------------------------------------------ static contacts
// wrench W_s (6) of body a's picked static contacts (static_wrench in static_contacts.h) and its vjp
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
    bool moving;  // on a moving static, whose angular velocity is angvel
    S angvel[3];
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
    bool on_moving = false;
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
      const Shape<S>& sh = w.shapes[ct.shape];
      if (sh.path != nullptr) {  // relative to the moving static's point x + arm (static_wrench)
        S pt[3], sv[3];
        for (int i = 0; i < 3; ++i) pt[i] = x[i] + ct.arm[i];
        shape_point_velocity(sh, pt, sv);
        for (int i = 0; i < 3; ++i) law.vel[i] -= sv[i];
        for (int i = 0; i < 3; ++i) ct.angvel[i] = sh.angvel[i];
        ct.moving = true;
        on_moving = on_moving || law.depth > 0;
      } else {
        ct.moving = false;
      }
      law.stiff = contact_stiffness(w, mass);
      law.unload = scaled_unload(w, w.unload_static[a * w.k + ct.shape]);
      law.mu = scaled_mu(w, w.mu_static[a * w.k + ct.shape]);
      law.inv_m = S(1) / mass;
      law.h = w.h;
      law.unload_velocity = w.unload_velocity;
      law.omega = w.omega;
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
    if (is_box_body(w, a) || on_moving)  // no roll stick on a box's corners, nor against a moving static
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

  // gs (STATE_WIDTH) += (d W_s / d st)^T mu, mu (6) the wrench's cotangent; gp (3) += its gradient
  // with respect to the logs of the World's physics factors (ContactLaw::add_material_gradient)
  void backward(const World<S>& w, int a, const S* mu, S* gs, S* gp) {
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
      law.add_material_gradient(gp);
      // vel = v + om x arm (- sv - sw x (x + arm - st) on a moving static)
      for (int i = 0; i < 3; ++i) vb[i] += velb[i];
      add_cross(ct.arm, velb, omb);
      add_cross(velb, om, armb);
      if (ct.moving) {
        add_cross(ct.angvel, velb, armb);
        add_cross(ct.angvel, velb, xb);
      }
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

}  // namespace dv
