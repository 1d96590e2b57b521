// A box body against a static box's edges, and against flat shapes with its corners
// (dejaview/sim/box_edges.py in C++; dejaview.sim.native).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "contact_law.h"

namespace dv {

// ------------------------------------------------------------------ static box edges
// A box body against a static box: the static's edges meet the body's exact faces at points
// EDGE_SPACING apart (box_edges.py, static_edge_points: per axis 0, 1, 2 its four edges at the
// other two axes' (-, -), (-, +), (+, -), (+, +) half extents, each edge_count points from -half to
// +half), and the body's spheres whose closest static point is on an edge or a corner are left
// out. A pick of such a point has sphere = -1 - (its index).
inline int edge_count(double half) {
  return std::max(2, static_cast<int>(std::nearbyint(2.0 * half / schema::EDGE_SPACING)) + 1);
}

// the static box's edge point e (world frame)
template <typename S>
void edge_point(const Shape<S>& sh, int e, S* out) {
  S local[3] = {S(0), S(0), S(0)};
  for (int axis = 0; axis < 3; ++axis) {
    const int n = edge_count(static_cast<double>(sh.half[axis]));
    if (e >= 4 * n) {
      e -= 4 * n;
      continue;
    }
    const int edge = e / n, i = e % n;
    const int o1 = axis == 0 ? 1 : 0, o2 = axis == 2 ? 1 : 2;
    local[axis] = S(i) * (S(2) * sh.half[axis] / S(n - 1)) - sh.half[axis];
    local[o1] = (edge / 2 ? S(1) : S(-1)) * sh.half[o1];
    local[o2] = (edge % 2 ? S(1) : S(-1)) * sh.half[o2];
    break;
  }
  for (int i = 0; i < 3; ++i)
    out[i] = local[0] * sh.rot[3 * i] + local[1] * sh.rot[3 * i + 1] + local[2] * sh.rot[3 * i + 2] + sh.trans[i];
}

// whether the static box's closest point to world point p is on an edge or a corner
template <typename S>
bool on_static_edge(const Shape<S>& sh, const S* p) {
  int outside = 0;
  for (int j = 0; j < 3; ++j) {
    const S l = (p[0] - sh.trans[0]) * sh.rot[j] + (p[1] - sh.trans[1]) * sh.rot[3 + j] +
                (p[2] - sh.trans[2]) * sh.rot[6 + j];
    if (std::abs(l) - sh.half[j] > 0) ++outside;
  }
  return outside >= 2;
}

// an edge point's contact with box body (half extents hb, centre x, world-from-body rot): its
// depth inside the box (min over the faces of half - |local|: the nearest face ax), the normal
// out of the static into the body (minus that face's normal) and the arm P - x
template <typename T, typename S>
void edge_contact(const S* P, const T* x, const T* rot, const S* hb, T& depth, T* n, T* arm, int* face = nullptr,
                  T* local = nullptr) {
  T rel[3], l[3];
  for (int i = 0; i < 3; ++i) rel[i] = P[i] - x[i];
  for (int j = 0; j < 3; ++j) l[j] = rel[0] * rot[j] + rel[1] * rot[3 + j] + rel[2] * rot[6 + j];
  int ax = 0;
  T best = hb[0] - abs(l[0]);
  for (int j = 1; j < 3; ++j) {
    T r = hb[j] - abs(l[j]);
    if (val(r) < val(best)) {
      best = r;
      ax = j;
    }
  }
  depth = relu(best);
  const S sg = val(l[ax]) < 0 ? S(-1) : S(1);
  for (int i = 0; i < 3; ++i) {
    n[i] = -sg * rot[3 * i + ax];
    arm[i] = rel[i];
  }
  if (face != nullptr) *face = ax;
  if (local != nullptr)
    for (int j = 0; j < 3; ++j) local[j] = l[j];
}

// box body a's picks of static box sh's edge points inside it, the cap deepest: per edge only the
// points where its line runs inside the body's box (clipped against the box's slabs in the body's
// frame, a point's margin either side; edge_contact decides), none while the box is farther from
// the static than its half diagonal
template <typename S>
void select_edges(const World<S>& w, int a, int k, const S* x, const S* rot, std::vector<Pick>& out) {
  const Shape<S>& sh = w.shapes[k];
  const S* hb = w.box_half + 3 * a;
  S dc;
  distance<S>(sh, x, dc, nullptr);
  if (dc > std::sqrt(hb[0] * hb[0] + hb[1] * hb[1] + hb[2] * hb[2])) return;
  thread_local std::vector<Pick> cand;
  cand.clear();
  int first = 0;
  for (int axis = 0; axis < 3; ++axis) {
    const int n = edge_count(static_cast<double>(sh.half[axis]));
    const S step = S(2) * sh.half[axis] / S(n - 1);
    for (int edge = 0; edge < 4; ++edge, first += n) {
      S p0[3], p1[3];
      edge_point(sh, first, p0);
      edge_point(sh, first + n - 1, p1);
      // the line p0 + t (p1 - p0) / |p1 - p0| in the body's frame: l(t) = l0 + t u
      S l0[3], u[3];
      const S len = S(2) * sh.half[axis];
      for (int j = 0; j < 3; ++j) {
        l0[j] = (p0[0] - x[0]) * rot[j] + (p0[1] - x[1]) * rot[3 + j] + (p0[2] - x[2]) * rot[6 + j];
        u[j] = ((p1[0] - p0[0]) * rot[j] + (p1[1] - p0[1]) * rot[3 + j] + (p1[2] - p0[2]) * rot[6 + j]) / len;
      }
      S t0 = S(0), t1 = len;
      for (int j = 0; j < 3 && t0 <= t1; ++j) {
        if (std::abs(u[j]) < S(schema::SLAB_PARALLEL)) {
          if (std::abs(l0[j]) >= hb[j]) t1 = S(-1);  // parallel to the slab and outside it
          continue;
        }
        S ta = (-hb[j] - l0[j]) / u[j], tb = (hb[j] - l0[j]) / u[j];
        if (ta > tb) std::swap(ta, tb);
        t0 = std::max(t0, ta);
        t1 = std::min(t1, tb);
      }
      if (t0 > t1) continue;
      const int i0 = std::max(0, static_cast<int>(std::floor(t0 / step)) - 1);
      const int i1 = std::min(n - 1, static_cast<int>(std::ceil(t1 / step)) + 1);
      for (int i = i0; i <= i1; ++i) {
        S P[3], depth, nn[3], arm[3];
        edge_point(sh, first + i, P);
        edge_contact<S, S>(P, x, rot, hb, depth, nn, arm);
        if (depth > 0) cand.push_back({k, -1 - (first + i), static_cast<double>(depth)});
      }
    }
  }
  if (static_cast<int>(cand.size()) > w.cap_static) {
    std::nth_element(cand.begin(), cand.begin() + w.cap_static, cand.end(),
                     [](const Pick& u, const Pick& v) { return u.depth > v.depth; });
    cand.resize(w.cap_static);
  }
  out.insert(out.end(), cand.begin(), cand.end());
}

template <typename S>
inline bool is_box_body(const World<S>& w, int a) {
  const S* hb = w.box_half + 3 * a;
  return hb[0] > 0 || hb[1] > 0 || hb[2] > 0;
}

// whether body a meets static shape k with its 8 corners (box_edges.CORNER_KINDS: a box body
// against a plane or a static box) rather than its packing
static_assert(schema::KIND_COUNT == 5, "corner_contacts names the flat kinds (box_edges.CORNER_KINDS)");

template <typename S>
inline bool corner_contacts(const World<S>& w, int a, int k) {
  const int kind = w.shapes[k].kind;
  return (kind == schema::KIND_PLANE || kind == schema::KIND_BOX) && is_box_body(w, a);
}

// sphere i of body a's static contacts: its centre c (3, body axes) and its radius; with corners
// (corner_contacts of the shape) the box's corner i (box_edges.box_corners: sign +1 along axis j
// where bit j of i is set, radius min(BOX_CORNER_RADIUS, min(half) / 4), centred that far
// inside), else its packing's sphere i
template <typename S>
inline S static_point(const World<S>& w, int a, bool corners, int i, S* c) {
  if (corners) {
    const S* hb = w.box_half + 3 * a;
    const S r = std::min(S(schema::BOX_CORNER_RADIUS), S(0.25) * std::min(hb[0], std::min(hb[1], hb[2])));
    for (int j = 0; j < 3; ++j) c[j] = ((i >> j) & 1 ? S(1) : S(-1)) * (hb[j] - r);
    return r;
  }
  const S* cc = w.centers + (static_cast<int64_t>(a) * w.s_max + i) * 3;
  for (int j = 0; j < 3; ++j) c[j] = cc[j];
  return w.radii[a * w.s_max + i];
}

}  // namespace dv
