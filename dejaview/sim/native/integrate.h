// Integration of one body over one substep (dejaview/sim/integrate.py in C++; dejaview.sim.native).
#pragma once

#include <cmath>

#include "contacts.h"

namespace dv {

// one semi-implicit Euler substep of one body from its state row st and wrench wr (6, gravity included)
template <typename T, typename S>
void integrate(const World<S>& w, int a, const T* st, const T* wr, T* out) {
  const T* q = st + STATE_ORIENTATION;
  T rot[9];
  quat_to_matrix(q, rot);
  const S hm = w.h / w.mass[a];
  T v[3], om[3], lw[3], gyro[3], rhs[3], acc[3], body[3], tmp[3];
  for (int i = 0; i < 3; ++i) v[i] = st[STATE_LINEAR_VELOCITY + i] + hm * wr[i];
  // I_w w and I_w^-1 (tau - gyro) as R (I (R^T u)): matrix-vector products only
  matvec_t(rot, st + STATE_ANGULAR_VELOCITY, body);
  matvec(w.inertia + 9 * a, body, tmp);
  matvec(rot, tmp, lw);
  cross3(st + STATE_ANGULAR_VELOCITY, lw, gyro);
  for (int i = 0; i < 3; ++i) rhs[i] = wr[3 + i] - gyro[i];
  matvec_t(rot, rhs, body);
  matvec(w.inv_inertia + 9 * a, body, tmp);
  matvec(rot, tmp, acc);
  for (int i = 0; i < 3; ++i) om[i] = st[STATE_ANGULAR_VELOCITY + i] + w.h * acc[i];
  for (int i = 0; i < 3; ++i) out[STATE_POSITION + i] = st[STATE_POSITION + i] + w.h * v[i];
  // rotvec_to_quat(om h) * q, renormalised
  T r[3] = {om[0] * w.h, om[1] * w.h, om[2] * w.h};
  const S eps = sizeof(S) == 8 ? S(schema::SMALL_ANGLE_F64) : S(schema::SMALL_ANGLE_F32);
  T sq = dot3(r, r);
  T sinc, co;
  if (val(sq) < eps * eps) {
    sinc = 0.5 - sq / S(48);
    co = 1.0 - sq / S(8);
  } else {
    T norm = sqrt(sq);
    T half = 0.5 * norm;
    sinc = sin(half) / norm;
    co = cos(half);
  }
  T e[4] = {co, sinc * r[0], sinc * r[1], sinc * r[2]};
  T qn[4];
  qn[0] = e[0] * q[0] - e[1] * q[1] - e[2] * q[2] - e[3] * q[3];
  qn[1] = e[0] * q[1] + e[1] * q[0] + e[2] * q[3] - e[3] * q[2];
  qn[2] = e[0] * q[2] - e[1] * q[3] + e[2] * q[0] + e[3] * q[1];
  qn[3] = e[0] * q[3] + e[1] * q[2] - e[2] * q[1] + e[3] * q[0];
  T len = sqrt(qn[0] * qn[0] + qn[1] * qn[1] + qn[2] * qn[2] + qn[3] * qn[3]);
  for (int i = 0; i < 4; ++i) out[STATE_ORIENTATION + i] = qn[i] / len;
  for (int i = 0; i < 3; ++i) {
    out[STATE_LINEAR_VELOCITY + i] = v[i];
    out[STATE_ANGULAR_VELOCITY + i] = om[i];
  }
}

}  // namespace dv
