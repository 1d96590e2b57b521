// Signed distance and outward normal of a point to each kind of static shape (StaticShape.distance
// and dejaview/sim/sdf.py in C++; dejaview.sim.native).
#pragma once

#include <cmath>
#include <cstdint>

#include "dual.h"
#include "world.h"

namespace dv {

// signed distance and outward normal of a world point, as StaticShape.distance (values, or a
// dual number of any width through distance() below); normal may be null: the distance alone
// (the same value, without the normal's divisions: contact selection)
static_assert(schema::KIND_COUNT == 5, "distance_direct has a branch per kind: add the new kind's");

template <typename T, typename S>
void distance_direct(const Shape<S>& sh, const T* pw, T& dist, T* normal) {
  T rel[3] = {pw[0] - sh.trans[0], pw[1] - sh.trans[1], pw[2] - sh.trans[2]};
  T p[3];
  for (int j = 0; j < 3; ++j) p[j] = rel[0] * sh.rot[j] + rel[1] * sh.rot[3 + j] + rel[2] * sh.rot[6 + j];
  T n[3];
  const S tiny2 = S(schema::NORMAL_EPS2);
  if (sh.kind == schema::KIND_PLANE) {  // plane z <= 0
    dist = p[2];
    n[0] = T(0); n[1] = T(0); n[2] = T(1);
  } else if (sh.kind == schema::KIND_BOX) {  // box
    T q[3], out[3];
    S sign[3];
    for (int c = 0; c < 3; ++c) {
      sign[c] = val(p[c]) < 0 ? S(-1) : S(1);
      q[c] = abs(p[c]) - sh.half[c];
      out[c] = clamp_min0(q[c]);
    }
    T len = sqrt(dot3(out, out) + tiny2);
    int axis = 0;
    for (int c = 1; c < 3; ++c)
      if (val(q[c]) > val(q[axis])) axis = c;
    if (val(q[axis]) > 0) {
      if (normal != nullptr)
        for (int c = 0; c < 3; ++c) n[c] = out[c] / len * sign[c];
      dist = len;
    } else {
      for (int c = 0; c < 3; ++c) n[c] = T(c == axis ? sign[c] : S(0));
      dist = clamp_max0(q[axis]);
    }
  } else if (sh.kind == schema::KIND_SPHERE) {  // sphere
    T len = sqrt(dot3(p, p) + tiny2);
    if (normal != nullptr)
      for (int c = 0; c < 3; ++c) n[c] = p[c] / len;
    dist = len - sh.radius;
  } else if (sh.kind == schema::KIND_CYLINDER) {  // cylinder along z
    T rlen = sqrt(p[0] * p[0] + p[1] * p[1] + tiny2);
    T radial[3] = {p[0] / rlen, p[1] / rlen, T(0)};
    T dr = rlen - sh.radius;
    T dz = abs(p[2]) - sh.half_height;
    S zs = val(p[2]) < 0 ? S(-1) : S(1);
    bool is_out = val(dr) > 0 || val(dz) > 0;
    if (is_out) {
      T c0 = clamp_min0(dr), c1 = clamp_min0(dz);
      T clen = sqrt(c0 * c0 + c1 * c1 + tiny2);
      T d0 = c0 / clen, d1 = c1 / clen;
      n[0] = radial[0] * d0; n[1] = radial[1] * d0; n[2] = d1 * zs;
      dist = clen;
    } else {
      dist = clamp_max0(vmax(dr, dz));
      if (val(dr) > val(dz)) {
        n[0] = radial[0]; n[1] = radial[1]; n[2] = T(0);
      } else {
        n[0] = T(0); n[1] = T(0); n[2] = T(zs);
      }
    }
  } else {  // grid (schema::KIND_GRID), trilinear
    const S size[3] = {S(sh.nx - 1), S(sh.ny - 1), S(sh.nz - 1)};
    T u_in[3], excess[3];
    int64_t i0[3];
    for (int c = 0; c < 3; ++c) {
      T u = (p[c] - sh.origin[c]) / sh.spacing;
      u_in[c] = vmin(vmax(u, T(0)), T(size[c]));
      excess[c] = (u - u_in[c]) * sh.spacing;
      S f0 = std::min(std::floor(val(u_in[c])), size[c] - 1);
      i0[c] = static_cast<int64_t>(std::max(f0, S(0)));
    }
    T f[3] = {u_in[0] - S(i0[0]), u_in[1] - S(i0[1]), u_in[2] - S(i0[2])};
    T g[3] = {T(0), T(0), T(0)};
    T d = T(0);
    const int64_t sy = sh.nz, sx = sh.ny * sh.nz;
    for (int a = 0; a < 2; ++a) {
      T wx = a ? f[0] : 1.0 - f[0];
      for (int b = 0; b < 2; ++b) {
        T wy = b ? f[1] : 1.0 - f[1];
        for (int c = 0; c < 2; ++c) {
          T wz = c ? f[2] : 1.0 - f[2];
          const S v = sh.grid[(i0[0] + a) * sx + (i0[1] + b) * sy + (i0[2] + c)];
          d = d + v * wx * wy * wz;
          g[0] = g[0] + v * S(2 * a - 1) * wy * wz;
          g[1] = g[1] + v * wx * S(2 * b - 1) * wz;
          g[2] = g[2] + v * wx * wy * S(2 * c - 1);
        }
      }
    }
    T elen = sqrt(dot3(excess, excess) + tiny2);
    if (val(elen) > S(schema::GRID_OUTSIDE)) {
      for (int c = 0; c < 3; ++c) n[c] = excess[c] / elen;
    } else {
      for (int c = 0; c < 3; ++c) n[c] = g[c] / sh.spacing;
    }
    dist = d + elen;
  }
  if (normal == nullptr) return;
  for (int i = 0; i < 3; ++i) normal[i] = n[0] * sh.rot[3 * i] + n[1] * sh.rot[3 * i + 1] + n[2] * sh.rot[3 * i + 2];
}

template <typename S>
inline void distance(const Shape<S>& sh, const S* pw, S& dist, S* normal) {
  distance_direct<S, S>(sh, pw, dist, normal);
}

// dual numbers: the field is a function of the 3 world coordinates only, so it runs on 3-wide
// duals and the 4 results are chained to the W tangents of the point (chain rule)
template <typename S, int W>
void distance(const Shape<S>& sh, const Dual<S, W>* pw, Dual<S, W>& dist, Dual<S, W>* normal) {
  using D3 = Dual<S, 3>;
  D3 p3[3], d3, n3[3];
  for (int c = 0; c < 3; ++c) {
    p3[c] = D3(pw[c].v);
    p3[c].d[c] = S(1);
  }
  distance_direct<D3, S>(sh, p3, d3, n3);
  auto chain3 = [&](const D3& x, Dual<S, W>& out) {
    out.v = x.v;
    for (int i = 0; i < Dual<S, W>::P; ++i)
      out.d[i] = x.d[0] * pw[0].d[i] + x.d[1] * pw[1].d[i] + x.d[2] * pw[2].d[i];
  };
  chain3(d3, dist);
  for (int c = 0; c < 3; ++c) chain3(n3[c], normal[c]);
}

}  // namespace dv
