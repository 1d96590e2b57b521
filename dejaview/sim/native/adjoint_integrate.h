// Reverse mode by hand (adjoint.h): one body's integration over a substep (integrate.h).
#pragma once

#include <cmath>

#include "adjoint_law.h"

namespace dv {

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
