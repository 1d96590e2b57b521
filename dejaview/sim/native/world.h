// The World as the engine reads it (filled by make_world, read_world.h, from the arrays of
// dejaview/sim/native/schema.py) and the offsets of a body's state row (dejaview.sim.native).
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

#include "schema.h"

namespace dv {

// a body's state row (dejaview.sim.state.STATE_LAYOUT): x, q, v, w at these offsets
using schema::STATE_ANGULAR_VELOCITY;
using schema::STATE_LINEAR_VELOCITY;
using schema::STATE_ORIENTATION;
using schema::STATE_POSITION;
using schema::STATE_WIDTH;

// ------------------------------------------------------------------ world
template <typename S>
struct Shape {
  int kind;  // schema::KIND_*
  S rot[9], trans[3], half[3], radius, half_height, origin[3], spacing, lipschitz;
  const S* grid;
  int64_t nx, ny, nz;
  // a moving static (a moving robot's link): its path (path_len rows of schema::PATH_WIDTH, one per
  // substep time, held after the last; pose_shapes copies the substep's row into rot and trans) and
  // its velocity now, which contacts' relative velocities take off; null for a static that stands
  const S* path = nullptr;
  int64_t path_len = 0;
  S vel[3] = {S(0), S(0), S(0)}, angvel[3] = {S(0), S(0), S(0)};
};

template <typename S>
struct World {
  int n, s_max, k, p;
  std::vector<int> count;  // real spheres per body
  std::vector<S> reach;    // largest sphere-centre distance from the centre of mass, per body, and for a
                           // box its corners' (statics meet its corners, body pairs its surface)
  const S *mass, *inertia, *inv_inertia, *centers, *radii, *bound, *inv_i_min;
  std::vector<Shape<S>> shapes;
  const S *mu_static, *unload_static;  // (N, K)
  const int64_t* pairs;                 // (P, 2)
  const S *mu_pair, *unload_pair, *mass_pair;
  const S* box_half;             // (N, 3): a box body's half extents, 0 for the others
  const int64_t* pair_surface;   // (P): the box (0: a, 1: b) whose surface the other's spheres meet, or -1
  S gravity[3];
  S h, omega, unload_velocity;
  int substeps, cap_static, cap_pair;
  // one candidate's physics, as factors on every pair's friction and unloading factor and on the
  // contact stiffness (rollout's `physics`: their logs; 1 where none is given)
  S mu_scale = S(1), unload_scale = S(1), stiff_scale = S(1);
  bool moving = false;        // some static has a path (a moving robot)
  int64_t first_substep = 0;  // the substep number the rollout starts at (where the paths stand)
};

// the moving statics of w posed at substep number j (from the rollout's start: first_substep + j):
// pose and velocity from their paths' row j, the last row after their ends
template <typename S>
void pose_shapes(World<S>& w, int64_t j) {
  using namespace schema;
  for (Shape<S>& sh : w.shapes) {
    if (sh.path == nullptr) continue;
    const S* row = sh.path + std::min(w.first_substep + j, sh.path_len - 1) * PATH_WIDTH;
    for (int i = 0; i < 9; ++i) sh.rot[i] = row[PATH_ROTATION + i];
    for (int i = 0; i < 3; ++i) {
      sh.trans[i] = row[PATH_TRANSLATION + i];
      sh.vel[i] = row[PATH_VELOCITY + i];
      sh.angvel[i] = row[PATH_ANGULAR_VELOCITY + i];
    }
  }
}

// velocity (3) of the point pt (3) of static shape sh, moving with it: vel + angvel x (pt - trans)
template <typename T, typename S>
inline void shape_point_velocity(const Shape<S>& sh, const T* pt, T* out) {
  T d[3];
  for (int i = 0; i < 3; ++i) d[i] = pt[i] - sh.trans[i];
  out[0] = sh.vel[0] + (sh.angvel[1] * d[2] - sh.angvel[2] * d[1]);
  out[1] = sh.vel[1] + (sh.angvel[2] * d[0] - sh.angvel[0] * d[2]);
  out[2] = sh.vel[2] + (sh.angvel[0] * d[1] - sh.angvel[1] * d[0]);
}

// the contact law's material of a pair, the candidate's physics applied: friction, unloading
// factor (its height above UNLOAD_MIN scaled, phi f + m (1 - f), phi itself at f = 1; kept at most
// 1: a restitution above 1 is impossible), stiffness of a contact with this (reduced) mass
template <typename S> inline S scaled_mu(const World<S>& w, S mu) { return mu * w.mu_scale; }
template <typename S> inline S scaled_unload(const World<S>& w, S phi) {
  return std::min(S(1), phi * w.unload_scale + S(schema::UNLOAD_MIN) * (S(1) - w.unload_scale));
}
template <typename S> inline S contact_stiffness(const World<S>& w, S mass) {
  return mass * w.omega * w.omega * w.stiff_scale;
}

// the time in which the roll stick stops a line's roll (line_contact.roll_stop_time): one substep at
// the default step, the contact's time scale ROLL_STOP_OMEGA_T / omega at finer ones
template <typename S>
S roll_stop_time(const World<S>& w) {
  return std::max(w.h, S(schema::ROLL_STOP_OMEGA_T) / w.omega);
}

}  // namespace dv
