// One candidate's rollout over its steps with what it records (states, the Jacobians Phi or the
// trace and pick log of reverse mode, where it diverged) and its adjoint back through those records
// (run_candidate, adjoint_candidate; dejaview.sim.native).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "step.h"

namespace dv {

// out = J phi, all dim x dim row-major; fixed sizes for 1 to 4 bodies so the loops unroll
template <typename S, int D>
void phi_update_fixed(const S* __restrict J, const S* __restrict phi, S* __restrict out) {
  for (int i = 0; i < D; ++i) {
    S acc[D] = {};
    for (int l = 0; l < D; ++l) {
      const S jil = J[i * D + l];
      for (int j = 0; j < D; ++j) acc[j] += jil * phi[l * D + j];
    }
    for (int j = 0; j < D; ++j) out[i * D + j] = acc[j];
  }
}

// several bodies: J is block-sparse (STATE_WIDTH-square blocks; body a's rows reach body b's columns only
// through a touching pair), so only the blocks marked in blk (N x N) are multiplied
template <typename S>
void phi_update(int dim, const S* J, const S* phi, S* out, const std::vector<char>& blk) {
  if (dim == STATE_WIDTH) return phi_update_fixed<S, STATE_WIDTH>(J, phi, out);
  const int n = dim / STATE_WIDTH;
  std::fill(out, out + static_cast<size_t>(dim) * dim, S(0));
  for (int a = 0; a < n; ++a)
    for (int b = 0; b < n; ++b) {
      if (!blk[a * n + b]) continue;
      for (int i = 0; i < STATE_WIDTH; ++i) {
        S* o = out + static_cast<size_t>(STATE_WIDTH * a + i) * dim;
        const S* jrow = J + static_cast<size_t>(STATE_WIDTH * a + i) * dim + STATE_WIDTH * b;
        for (int l = 0; l < STATE_WIDTH; ++l) {
          const S jil = jrow[l];
          const S* prow = phi + static_cast<size_t>(STATE_WIDTH * b + l) * dim;
          for (int j = 0; j < dim; ++j) o[j] += jil * prow[j];
        }
      }
    }
}

// Divergence check of forward simulations (dejaview.sim.divergence): the first quantity of body
// state row s that is not finite or out of range -- 0 position (|coordinate| > reach),
// 1 orientation, 2 linear velocity (|v| > speed), 3 angular velocity (|w| bound > speed) -- or -1.
template <typename S>
inline int diverged(const S* s, S reach, S speed, S bound) {
  const S *x = s + STATE_POSITION, *q = s + STATE_ORIENTATION;
  const S *v = s + STATE_LINEAR_VELOCITY, *om = s + STATE_ANGULAR_VELOCITY;
  for (int i = 0; i < 3; ++i)
    if (!(std::abs(x[i]) <= reach)) return 0;  // NaN fails every comparison
  for (int i = 0; i < 4; ++i)
    if (!std::isfinite(q[i])) return 1;
  const S v2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  if (!(v2 <= speed * speed)) return 2;
  const S w2 = om[0] * om[0] + om[1] * om[1] + om[2] * om[2];
  if (!(w2 * bound * bound <= speed * speed)) return 3;
  return -1;
}

// limits: nullptr, or {reach, speed}: a body whose state diverges (above) ends the candidate; its
// state is then the last record written, status = {step, body, quantity, record} and the records
// after it are NaN. status stays {-1, -1, -1, -1} otherwise.
template <typename S>
void init_scratch(const World<S>& w, Scratch<S>& sc) {
  const int n = w.n;
  sc.picks.resize(n);
  sc.pair_picks.resize(w.p);
  sc.rot.resize(9 * n);
  sc.wrench.resize(6 * n);
  sc.next.resize(STATE_WIDTH * n);
  sc.key.assign(static_cast<size_t>(n) * w.k * w.s_max, -std::numeric_limits<S>::infinity());
  sc.floor.assign(static_cast<size_t>(n) * w.k, -std::numeric_limits<S>::infinity());
  sc.keymin.assign(static_cast<size_t>(n) * w.k, -std::numeric_limits<S>::infinity());
  sc.last.assign(static_cast<size_t>(12) * n, std::numeric_limits<S>::infinity());
  sc.move.assign(n, S(0));
  sc.travel.assign(n, S(0));
  sc.placed.assign(n, 0);
  sc.pair_clear.assign(w.p, -std::numeric_limits<S>::infinity());
}

// Substep states kept for reverse mode (trace): per step the states before substeps k0..substeps-1,
// k0 = 1 when every step is recorded (the state before substep 0 is then the previous record, or
// init), else 0.
inline int trace_first(int64_t record_every) { return record_every == 1 ? 1 : 0; }

// a moving robot's statics change pose every substep: a candidate poses its own copy of the World
template <typename S>
struct Posed {
  World<S> own;
  const World<S>* at;
  explicit Posed(const World<S>& w) : at(&w) {
    if (w.moving) {
      own = w;
      at = &own;
    }
  }
  // the statics at substep number j of the rollout (from its first_substep)
  const World<S>& operator()(int64_t j) {
    if (at == &own) pose_shapes(own, j);
    return *at;
  }
};

template <typename S>
void run_candidate(const World<S>& world, const S* init, int64_t steps, int64_t record_every, bool with_jac,
                   S* rec_states, S* rec_phi, const S* limits, int64_t* status, S* trace = nullptr,
                   PickLog* log = nullptr) {
  Posed<S> posed(world);
  const World<S>& w = world;
  const int n = w.n;
  const int dim = STATE_WIDTH * n;
  Scratch<S> sc;
  init_scratch(w, sc);
  const int k0 = trace_first(record_every);
  std::vector<S> state(init, init + dim);
  std::vector<S> phi, tmp;
  if (with_jac) {
    phi.assign(static_cast<size_t>(dim) * dim, S(0));
    for (int i = 0; i < dim; ++i) phi[static_cast<size_t>(i) * dim + i] = S(1);
    tmp.resize(static_cast<size_t>(dim) * dim);
    sc.jac.resize(static_cast<size_t>(dim) * dim);
    sc.dws.resize(static_cast<size_t>(6 * n) * dim);
  }
  int64_t r = 0;
  for (int64_t step = 1; step <= steps; ++step) {
    for (int k = 0; k < w.substeps; ++k) {
      if (trace != nullptr && k >= k0) {
        std::copy(state.begin(), state.end(), trace);
        trace += dim;
      }
      const World<S>& wk = posed((step - 1) * w.substeps + k);
      if (!with_jac) {
        substep<S>(wk, state.data(), sc, nullptr);
        if (log != nullptr)
          for (int a = 0; a < n; ++a) {
            log->counts.push_back(static_cast<int32_t>(sc.picks[a].size()));
            for (const Pick& pk : sc.picks[a])
              log->picks.push_back(static_cast<uint32_t>(pk.shape) << 16 |
                                  (static_cast<uint32_t>(pk.sphere) & 0xFFFFu));
          }
        continue;
      }
      substep(wk, state.data(), sc, sc.jac.data());
      phi_update<S>(dim, sc.jac.data(), phi.data(), tmp.data(), sc.blk);  // phi <- J phi
      phi.swap(tmp);
    }
    int bad_body = -1, bad_quantity = -1;
    if (limits) {
      for (int a = 0; a < n && bad_body < 0; ++a) {
        bad_quantity = diverged<S>(state.data() + STATE_WIDTH * a, limits[0], limits[1], w.bound[a]);
        if (bad_quantity >= 0) bad_body = a;
      }
    }
    if (bad_body >= 0 || step % record_every == 0 || step == steps) {
      std::copy(state.begin(), state.end(), rec_states + r * dim);
      if (with_jac) std::copy(phi.begin(), phi.end(), rec_phi + r * static_cast<int64_t>(dim) * dim);
      ++r;
    }
    if (bad_body >= 0) {
      status[0] = step; status[1] = bad_body; status[2] = bad_quantity; status[3] = r - 1;
      const int64_t records = (steps + record_every - 1) / record_every;
      const S nan = std::numeric_limits<S>::quiet_NaN();
      std::fill(rec_states + r * dim, rec_states + records * dim, nan);
      if (with_jac)
        std::fill(rec_phi + r * static_cast<int64_t>(dim) * dim, rec_phi + records * static_cast<int64_t>(dim) * dim, nan);
      return;
    }
  }
}

// Reverse mode of one candidate from its rollout (init, records, trace of run_candidate):
// grad_init = sum_t Phi_t^T grad_t, as lam <- J^T lam backwards through the substeps; out_phys (3),
// where given, the gradient with respect to the logs of w's physics factors (World::mu_scale, ...).
template <typename S>
void adjoint_candidate(const World<S>& world, const S* init, int64_t steps, int64_t record_every,
                       const S* rec_states, const S* trace, const S* grad, S* out,
                       const int32_t* counts = nullptr, const uint32_t* picks = nullptr, int64_t total = 0,
                       S* out_phys = nullptr) {
  Posed<S> posed(world);
  const World<S>& w = world;
  const int n = w.n;
  const int dim = STATE_WIDTH * n;
  Scratch<S> sc;
  init_scratch(w, sc);
  const int k0 = trace_first(record_every);
  const int per_step = w.substeps - k0;
  std::vector<S> lam(dim, S(0));
  int64_t r = (steps + record_every - 1) / record_every - 1;
  for (int64_t step = steps; step >= 1; --step) {
    if (step % record_every == 0 || step == steps) {
      const S* g = grad + r * dim;
      for (int i = 0; i < dim; ++i) lam[i] += g[i];
      --r;
    }
    for (int k = w.substeps - 1; k >= 0; --k) {
      const S* s;
      if (k >= k0) s = trace + ((step - 1) * per_step + (k - k0)) * static_cast<int64_t>(dim);
      else s = step == 1 ? init : rec_states + (step - 2) * static_cast<int64_t>(dim);  // record_every 1
      if (counts != nullptr) {  // this substep's logged picks end where the next one's begin
        sc.logged = counts + ((step - 1) * w.substeps + k) * static_cast<int64_t>(n);
        for (int a = 0; a < n; ++a) total -= sc.logged[a];
        sc.logged_picks = picks + total;
      }
      substep_adjoint(posed((step - 1) * w.substeps + k), s, sc, lam.data());
    }
  }
  std::copy(lam.begin(), lam.end(), out);
  if (out_phys != nullptr) std::copy(sc.gphys, sc.gphys + 3, out_phys);
}

// w with one candidate's physics: phys (3) the logs of its friction, unloading and stiffness factors
template <typename S>
World<S> with_physics(const World<S>& w, const S* phys) {
  World<S> v = w;
  v.mu_scale = std::exp(phys[0]);
  v.unload_scale = std::exp(phys[1]);
  v.stiff_scale = std::exp(phys[2]);
  return v;
}

}  // namespace dv
