// Forward-mode dual numbers Dual<S, W> and the small vector algebra the engine's templates use
// (dejaview.sim.native; part of rollout.cpp's extension).
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

namespace dv {

// ------------------------------------------------------------------ dual numbers
#ifndef DV_PAD
#define DV_PAD 4
#endif
// W tangents, stored padded to a multiple of DV_PAD (zeros) so every loop is whole vectors
template <typename S, int W>
struct Dual {
  static constexpr int P = (W + DV_PAD - 1) / DV_PAD * DV_PAD;
  S d[P];
  S v;
  Dual() = default;
  Dual(S x) : v(x) {  // NOLINT: a constant
    for (int i = 0; i < P; ++i) d[i] = S(0);
  }
};

template <typename S> inline S val(S x) { return x; }
template <typename S, int W> inline S val(const Dual<S, W>& x) { return x.v; }

#define DV_D template <typename S, int W> inline Dual<S, W>
DV_D operator+(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v + b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] + b.d[i];
  return r;
}
DV_D operator-(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v - b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] - b.d[i];
  return r;
}
DV_D operator-(const Dual<S, W>& a) {
  Dual<S, W> r; r.v = -a.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = -a.d[i];
  return r;
}
DV_D operator*(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v * b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] * b.v + a.v * b.d[i];
  return r;
}
DV_D operator/(const Dual<S, W>& a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a.v / b.v;
  const S inv = S(1) / b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = (a.d[i] - r.v * b.d[i]) * inv;
  return r;
}
DV_D operator+(const Dual<S, W>& a, S b) { Dual<S, W> r = a; r.v += b; return r; }
DV_D operator+(S b, const Dual<S, W>& a) { Dual<S, W> r = a; r.v += b; return r; }
DV_D operator-(const Dual<S, W>& a, S b) { Dual<S, W> r = a; r.v -= b; return r; }
DV_D operator-(S b, const Dual<S, W>& a) {
  Dual<S, W> r; r.v = b - a.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = -a.d[i];
  return r;
}
DV_D operator*(const Dual<S, W>& a, S b) {
  Dual<S, W> r; r.v = a.v * b;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] * b;
  return r;
}
DV_D operator*(S b, const Dual<S, W>& a) { return a * b; }
DV_D operator/(const Dual<S, W>& a, S b) {
  Dual<S, W> r; r.v = a.v / b;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = a.d[i] / b;
  return r;
}
DV_D operator/(S a, const Dual<S, W>& b) {
  Dual<S, W> r; r.v = a / b.v;
  const S k = -r.v / b.v;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = k * b.d[i];
  return r;
}
DV_D chain(const Dual<S, W>& a, S value, S slope) {
  Dual<S, W> r; r.v = value;
  for (int i = 0; i < Dual<S, W>::P; ++i) r.d[i] = slope * a.d[i];
  return r;
}
DV_D sqrt(const Dual<S, W>& a) { const S s = std::sqrt(a.v); return chain(a, s, S(0.5) / s); }
DV_D sin(const Dual<S, W>& a) { return chain(a, std::sin(a.v), std::cos(a.v)); }
DV_D cos(const Dual<S, W>& a) { return chain(a, std::cos(a.v), -std::sin(a.v)); }
DV_D sigmoid(const Dual<S, W>& a) {
  const S s = S(1) / (S(1) + std::exp(-a.v));
  return chain(a, s, s * (S(1) - s));
}
DV_D pow(const Dual<S, W>& a, S p) {
  return chain(a, std::pow(a.v, p), p * std::pow(a.v, p - S(1)));
}
DV_D abs(const Dual<S, W>& a) {
  return chain(a, std::abs(a.v), a.v > 0 ? S(1) : (a.v < 0 ? S(-1) : S(0)));
}
#undef DV_D
template <typename S> inline S sigmoid(S a) { return S(1) / (S(1) + std::exp(-a)); }
using std::abs;
using std::cos;
using std::pow;
using std::sin;
using std::sqrt;

// torch's gradient conventions at kinks: relu passes nothing at 0, clamp(min) passes at equality
template <typename T> inline T relu(const T& a) { return val(a) > 0 ? a : T(0); }
template <typename T> inline T clamp_min0(const T& a) { return val(a) >= 0 ? a : T(0); }
template <typename T> inline T clamp_max0(const T& a) { return val(a) <= 0 ? a : T(0); }
template <typename T> inline const T& vmax(const T& a, const T& b) { return val(b) > val(a) ? b : a; }
template <typename T> inline const T& vmin(const T& a, const T& b) { return val(b) < val(a) ? b : a; }
// plain numbers by value: a select, not a branch (the contact law's loops vectorise)
inline double vmax(double a, double b) { return b > a ? b : a; }
inline double vmin(double a, double b) { return b < a ? b : a; }

// ------------------------------------------------------------------ small vector algebra
template <typename T> inline T dot3(const T* a, const T* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
template <typename T> inline void cross3(const T* a, const T* b, T* r) {
  T r0 = a[1] * b[2] - a[2] * b[1];
  T r1 = a[2] * b[0] - a[0] * b[2];
  T r2 = a[0] * b[1] - a[1] * b[0];
  r[0] = r0; r[1] = r1; r[2] = r2;
}
// r = M v, M row-major 3 x 3
template <typename T, typename M> inline void matvec(const M* m, const T* v, T* r) {
#pragma GCC unroll 3
  for (int i = 0; i < 3; ++i) r[i] = m[3 * i] * v[0] + m[3 * i + 1] * v[1] + m[3 * i + 2] * v[2];
}
// r = M^T v
template <typename T, typename M> inline void matvec_t(const M* m, const T* v, T* r) {
#pragma GCC unroll 3
  for (int i = 0; i < 3; ++i) r[i] = m[i] * v[0] + m[3 + i] * v[1] + m[6 + i] * v[2];
}
// rotation matrix of a unit quaternion (w x y z), as dejaview.sim.rotation.quat_to_matrix
template <typename T> inline void quat_to_matrix(const T* q, T* r) {
  const T &w = q[0], &x = q[1], &y = q[2], &z = q[3];
  r[0] = 1.0 - 2.0 * (y * y) - 2.0 * (z * z);
  r[1] = 2.0 * (x * y) - 2.0 * (z * w);
  r[2] = 2.0 * (x * z) + 2.0 * (y * w);
  r[3] = 2.0 * (x * y) + 2.0 * (z * w);
  r[4] = 1.0 - 2.0 * (x * x) - 2.0 * (z * z);
  r[5] = 2.0 * (y * z) - 2.0 * (x * w);
  r[6] = 2.0 * (x * z) - 2.0 * (y * w);
  r[7] = 2.0 * (y * z) + 2.0 * (x * w);
  r[8] = 1.0 - 2.0 * (x * x) - 2.0 * (y * y);
}
// R A R^T with A a constant (body-frame) symmetric matrix
template <typename T, typename S> inline void rotate_tensor(const T* r, const S* a, T* out) {
  T ra[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) ra[3 * i + j] = r[3 * i] * a[j] + r[3 * i + 1] * a[3 + j] + r[3 * i + 2] * a[6 + j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      out[3 * i + j] = ra[3 * i] * r[3 * j] + ra[3 * i + 1] * r[3 * j + 1] + ra[3 * i + 2] * r[3 * j + 2];
}

}  // namespace dv
