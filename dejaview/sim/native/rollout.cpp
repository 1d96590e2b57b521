// Native rollout of the sphere-packing simulator (dejaview.sim.native).
//
// The same model as dejaview/sim/contacts.py and dejaview/sim/integrate.py, written once as
// templates over the number type T: plain floats for values, and forward-mode dual numbers
// Dual<S, W> (a value and W tangents) for exact Jacobians. A substep's Jacobian is assembled from
// three small dual passes per body, whatever the number of spheres:
//
//   static contacts  W_s(s_a)          Dual<13>: d W_s / d s_a            (6 x 13)
//   body pair (a, b) W_p(s_a, s_b)     Dual<26>: d W_p / d (s_a, s_b)     (12 x 26)
//   integration      s_a' = I(s_a, W_a) Dual<19>: d s_a' / d (s_a, W_a)   (13 x 19)
//
// with s = (x, q, v, w) (13 numbers) and W = (F, tau). Forward mode: the rollout carries the
// product of the substep Jacobians, Phi = d s_t / d s_0 (13N x 13N), and returns it at every
// recorded step; a Jacobian-vector product is Phi_t v (and sum_t Phi_t^T g_t a vector-Jacobian
// product, DEJAVIEW_NATIVE_GRADIENT=phi). Reverse mode: the rollout keeps its substep states (the
// trace) and adjoint() runs lam <- J^T lam back through them (substep_adjoint) by the
// hand-written vector-Jacobian products of adjoint.h, which the dual passes hold to account.
//
// Contact selection (which spheres touch) is made on values, as the torch code's topk on detached
// depths; spheres that do not touch carry exactly zero force and zero derivative there, so they are
// skipped. Culling, all of it exact: a body whose centre is farther from a static shape than
// L * bound (L the shape's Lipschitz bound, bound the body's bounding radius) skips the shape; each
// sphere keeps a lower bound on its clearance to each shape, lowered every substep by L times how
// far the body moved, and is looked at only when the bound reaches zero (select_static); a body
// pair pairs only the spheres within reach of the other body's bounding sphere (select_pair).
#include <torch/extension.h>

#include <algorithm>
#include <atomic>
#include <exception>
#include <mutex>
#include <thread>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "adjoint.h"
#include "contacts.h"
#include "dual.h"
#include "integrate.h"
#include "schema.h"

namespace dv {

// ------------------------------------------------------------------ one candidate
template <typename S>
struct Scratch {
  std::vector<std::vector<Pick>> picks;          // per body
  std::vector<std::vector<PairPick>> pair_picks;  // per pair
  std::vector<S> rot;                             // (N, 9)
  std::vector<S> wrench;                          // (N, 6)
  std::vector<S> next;                            // (N, 13)
  std::vector<S> jac, dws;                        // substep Jacobian (13N)^2, dW/ds (6N x 13N)
  std::vector<S> key;                             // (N, K, s_max) clearance bounds (select_static)
  std::vector<S> floor, keymin;                   // (N, K) ... of every sphere, the smallest key
  std::vector<S> last;                            // (N, 12) position and rotation at the last selection
  std::vector<char> blk;                          // (N, N) nonzero 13 x 13 blocks of the Jacobian
  std::vector<StaticAdjoint<S>> static_adj;       // (N) static contacts' values for the way back
  std::vector<PairAdjoint<S>> pair_adj;           // (P) ... body pairs'
  std::vector<S> move;                            // (N) how far a sphere, corner or box surface point of each
                                                  // body moved this substep (World::reach)
  std::vector<S> travel;                          // (N) the sum of move over the substeps
  std::vector<char> placed;                       // (N) selected before (last holds its pose)
  std::vector<S> pair_clear;                      // (P) clearance bound of each pair (select_pair)
  const int32_t* logged = nullptr;                // (N) picks of this substep per body (PickLog), or null
  const uint32_t* logged_picks = nullptr;         // ... and the picks themselves, body after body
};

// The static picks of every substep of a traced rollout (reverse mode reads them instead of
// selecting again: the same picks, in the same order, as select_static is exact and deterministic).
// counts (steps * substeps, N): picks per substep and body; picks: shape << 16 | sphere (the low
// 16 bits signed: a static box's edge point is sphere -1 - its index), substep after substep, body
// after body. Kept only while the scene's indices fit those bits.
struct PickLog {
  std::vector<int32_t> counts;
  std::vector<uint32_t> picks;
};

template <typename S>
bool pick_log_fits(const World<S>& w) {
  int64_t edges = 0;  // a static box's edge points are picks with sphere = -1 - (their index)
  for (const Shape<S>& sh : w.shapes)
    if (sh.kind == schema::KIND_BOX)
      edges = std::max<int64_t>(edges, 4 * (int64_t(edge_count(sh.half[0])) + edge_count(sh.half[1]) +
                                            edge_count(sh.half[2])));
  return w.k <= 0xFFFF && w.s_max <= 0x7FFF && edges <= 0x8000;
}

// which spheres touch at state (contact selection on values, the clearance bounds of sc updated).
// need (N, or null for all): bodies whose contacts are wanted; the others get no static picks,
// and a pair of two such bodies none (reverse mode skips bodies its adjoint has not reached).
// With a pick log (sc.logged, reverse mode) the static picks are read from it, not selected.
//
// Pairs keep a lower bound on the clearance |p_i - p_j| - r_i - r_j of every sphere pair, set
// by select_pair and lowered every substep by how far either body moved: a pair whose bound
// stays above CLEAR_MARGIN cannot touch and is skipped (exact, as select_static's bounds).
template <typename S>
void select_contacts(const World<S>& w, const S* state, Scratch<S>& sc, const char* need = nullptr) {
  const int n = w.n;
  const uint32_t* logged = sc.logged_picks;  // body a's logged picks, when there is a log
  for (int a = 0; a < n; ++a) {
    S* rot = &sc.rot[9 * a];
    S* last = &sc.last[12 * a];
    quat_to_matrix(state + STATE_WIDTH * a + STATE_ORIENTATION, rot);
    const S* x = state + STATE_WIDTH * a + STATE_POSITION;
    S dx = 0, dr = 0;
    for (int i = 0; i < 3; ++i) dx += (x[i] - last[i]) * (x[i] - last[i]);
    for (int i = 0; i < 9; ++i) dr += (rot[i] - last[3 + i]) * (rot[i] - last[3 + i]);
    // |p_i' - p_i| <= |x' - x| + |R' - R|_F |c_i|
    // (no previous selection: every bound is -inf, nothing to lower)
    const S move = sc.placed[a] ? std::sqrt(dx) + std::sqrt(dr) * w.reach[a] : S(0);
    sc.placed[a] = 1;
    for (int i = 0; i < 3; ++i) last[i] = x[i];
    for (int i = 0; i < 9; ++i) last[3 + i] = rot[i];
    sc.move[a] = move;
    sc.travel[a] += move;
    const uint32_t* first = logged;
    if (sc.logged != nullptr) logged += sc.logged[a];
    if (need != nullptr && !need[a]) {
      sc.picks[a].clear();
      continue;
    }
    if (sc.logged != nullptr) {
      sc.picks[a].clear();
      for (int j = 0; j < sc.logged[a]; ++j)
        sc.picks[a].push_back({static_cast<int>(first[j] >> 16),
                               static_cast<int>(static_cast<int16_t>(first[j] & 0xFFFF)), 0.0});
      continue;
    }
    select_static(w, a, state + STATE_WIDTH * a, rot, sc.picks[a],
                  &sc.key[static_cast<int64_t>(a) * w.k * w.s_max], &sc.floor[static_cast<int64_t>(a) * w.k],
                  &sc.keymin[static_cast<int64_t>(a) * w.k], sc.travel[a]);
  }
  for (int pi = 0; pi < w.p; ++pi) {
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    S& bound = sc.pair_clear[pi];
    bound -= sc.move[a] + sc.move[b];
    if (bound > S(CLEAR_MARGIN) || (need != nullptr && !need[a] && !need[b])) {
      sc.pair_picks[pi].clear();
      continue;
    }
    bound = select_pair(w, pi, a, b, state + STATE_WIDTH * a, state + STATE_WIDTH * b, &sc.rot[9 * a],
                        &sc.rot[9 * b], sc.pair_picks[pi]);
  }
}

template <typename S>
void substep(const World<S>& w, S* state, Scratch<S>& sc, S* jac /* (13N)^2 or null */) {
  const int n = w.n;
  const int dim = STATE_WIDTH * n;
  select_contacts(w, state, sc);
  if (jac == nullptr) {
    for (int a = 0; a < n; ++a) static_wrench<S, S>(w, a, state + STATE_WIDTH * a, sc.picks[a], &sc.wrench[6 * a]);
    for (int pi = 0; pi < w.p; ++pi) {
      if (sc.pair_picks[pi].empty()) continue;
      const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
      S o[12];
      pair_wrench<S, S>(w, pi, state + STATE_WIDTH * a, state + STATE_WIDTH * b, sc.pair_picks[pi], o);
      for (int i = 0; i < 6; ++i) {
        sc.wrench[6 * a + i] += o[i];
        sc.wrench[6 * b + i] += o[6 + i];
      }
    }
    for (int a = 0; a < n; ++a) {
      for (int i = 0; i < 3; ++i) sc.wrench[6 * a + i] += w.mass[a] * w.gravity[i];
      integrate<S, S>(w, a, state + STATE_WIDTH * a, &sc.wrench[6 * a], &sc.next[STATE_WIDTH * a]);
    }
    std::copy(sc.next.begin(), sc.next.end(), state);
    return;
  }
  // Jacobian: dW/ds per body (6 x 13N), then integration
  std::fill(sc.dws.begin(), sc.dws.end(), S(0));  // (N, 6, 13N)
  sc.blk.assign(static_cast<size_t>(n) * n, 0);
  for (int a = 0; a < n; ++a) sc.blk[a * n + a] = 1;
  for (int a = 0; a < n; ++a) {
    using D = Dual<S, STATE_WIDTH>;
    D st[STATE_WIDTH], o[6];
    seed_state(state + STATE_WIDTH * a, st, 0);
    static_wrench<D, S>(w, a, st, sc.picks[a], o);
    for (int i = 0; i < 6; ++i) {
      sc.wrench[6 * a + i] = o[i].v;
      for (int j = 0; j < STATE_WIDTH; ++j)
        sc.dws[(static_cast<int64_t>(6 * a + i)) * dim + STATE_WIDTH * a + j] = o[i].d[j];
    }
  }
  for (int pi = 0; pi < w.p; ++pi) {
    if (sc.pair_picks[pi].empty()) continue;
    using D = Dual<S, 2 * STATE_WIDTH>;
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    D sa[STATE_WIDTH], sb[STATE_WIDTH], o[12];
    seed_state(state + STATE_WIDTH * a, sa, 0);
    seed_state(state + STATE_WIDTH * b, sb, STATE_WIDTH);
    pair_wrench<D, S>(w, pi, sa, sb, sc.pair_picks[pi], o);
    sc.blk[a * n + b] = sc.blk[b * n + a] = 1;
    for (int half = 0; half < 2; ++half) {
      const int body = half ? b : a;
      for (int i = 0; i < 6; ++i) {
        const D& f = o[6 * half + i];
        sc.wrench[6 * body + i] += f.v;
        S* row = &sc.dws[static_cast<int64_t>(6 * body + i) * dim];
        for (int j = 0; j < STATE_WIDTH; ++j) {
          row[STATE_WIDTH * a + j] += f.d[j];
          row[STATE_WIDTH * b + j] += f.d[STATE_WIDTH + j];
        }
      }
    }
  }
  std::fill(sc.jac.begin(), sc.jac.end(), S(0));
  for (int a = 0; a < n; ++a) {
    using D = Dual<S, STATE_WIDTH + 6>;
    D st[STATE_WIDTH], wr[6], o[STATE_WIDTH];
    seed_state(state + STATE_WIDTH * a, st, 0);
    for (int i = 0; i < 6; ++i) {
      S value = sc.wrench[6 * a + i] + (i < 3 ? w.mass[a] * w.gravity[i] : S(0));
      wr[i] = D(value);
      wr[i].d[STATE_WIDTH + i] = S(1);
    }
    integrate<D, S>(w, a, st, wr, o);
    for (int i = 0; i < STATE_WIDTH; ++i) {
      sc.next[STATE_WIDTH * a + i] = o[i].v;
      S* row = jac + static_cast<int64_t>(STATE_WIDTH * a + i) * dim;
      for (int j = 0; j < STATE_WIDTH; ++j) row[STATE_WIDTH * a + j] += o[i].d[j];
      for (int k = 0; k < 6; ++k) {
        const S g = o[i].d[STATE_WIDTH + k];
        if (g == S(0)) continue;
        const S* dw = &sc.dws[static_cast<int64_t>(6 * a + k) * dim];
        for (int j = 0; j < dim; ++j) row[j] += g * dw[j];
      }
    }
  }
  std::copy(sc.next.begin(), sc.next.end(), state);
}

// Reverse mode, one substep: lam <- J(state)^T lam, J = d state' / d state the substep's Jacobian,
// by the hand-written vector-Jacobian products of adjoint.h (the dual passes of substep(..., jac)
// are its reference): with s_a' = I(s_a, W_a) and W_a = W_s(s_a) + sum over touching pairs
// W_p(s_a, s_b),
//   mu_a = (dI/dW_a)^T lam_a,  lam_a <- (dI/ds_a)^T lam_a + (dW_s/ds_a)^T mu_a + pair terms.
// A body whose adjoint lam_a is zero has mu_a = 0: its integration and static contacts are then
// skipped, and a pair only when both of its bodies are (bodies no contact chain connects to the
// loss cost a value pass of their pairs at most).
template <typename S>
void substep_adjoint(const World<S>& w, const S* state, Scratch<S>& sc, S* lam) {
  const int n = w.n;
  std::vector<char>& live = sc.blk;  // per body: adjoint nonzero
  live.assign(n, 0);
  for (int a = 0; a < n; ++a)
    for (int i = 0; i < STATE_WIDTH; ++i)
      if (lam[STATE_WIDTH * a + i] != S(0)) { live[a] = 1; break; }
  select_contacts(w, state, sc, live.data());
  // wrench values of every live body, keeping what the way back needs
  std::fill(sc.wrench.begin(), sc.wrench.end(), S(0));
  sc.next.assign(STATE_WIDTH * n, S(0));  // the new adjoint
  std::vector<S>& mu = sc.dws;   // (N, 6)
  mu.assign(6 * n, S(0));
  sc.static_adj.resize(n);
  sc.pair_adj.resize(w.p);
  for (int a = 0; a < n; ++a)
    if (live[a]) sc.static_adj[a].forward(w, a, state + STATE_WIDTH * a, sc.picks[a], &sc.wrench[6 * a]);
  for (int pi = 0; pi < w.p; ++pi) {
    if (sc.pair_picks[pi].empty()) continue;
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    if (!live[a] && !live[b]) continue;
    S o[12];
    sc.pair_adj[pi].forward(w, pi, state + STATE_WIDTH * a, state + STATE_WIDTH * b, sc.pair_picks[pi], o);
    for (int i = 0; i < 6; ++i) {
      sc.wrench[6 * a + i] += o[i];
      sc.wrench[6 * b + i] += o[6 + i];
    }
  }
  // integration of each live body: its own adjoint and mu, then its static contacts
  for (int a = 0; a < n; ++a) {
    if (!live[a]) continue;
    S wr[6];
    for (int i = 0; i < 6; ++i) wr[i] = sc.wrench[6 * a + i] + (i < 3 ? w.mass[a] * w.gravity[i] : S(0));
    integrate_vjp(w, a, state + STATE_WIDTH * a, wr, lam + STATE_WIDTH * a, &sc.next[STATE_WIDTH * a],
                  &mu[6 * a]);
    sc.static_adj[a].backward(w, a, &mu[6 * a], &sc.next[STATE_WIDTH * a]);
  }
  for (int pi = 0; pi < w.p; ++pi) {
    if (sc.pair_picks[pi].empty()) continue;
    const int a = static_cast<int>(w.pairs[2 * pi]), b = static_cast<int>(w.pairs[2 * pi + 1]);
    if (!live[a] && !live[b]) continue;
    S m[12];
    for (int i = 0; i < 6; ++i) {
      m[i] = mu[6 * a + i];
      m[6 + i] = mu[6 * b + i];
    }
    sc.pair_adj[pi].backward(w, state + STATE_WIDTH * a, state + STATE_WIDTH * b, m, &sc.next[STATE_WIDTH * a],
                             &sc.next[STATE_WIDTH * b]);
  }
  std::copy(sc.next.begin(), sc.next.end(), lam);
}

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

// several bodies: J is block-sparse (13 x 13 blocks; body a's rows reach body b's columns only
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

template <typename S>
void run_candidate(const World<S>& w, const S* init, int64_t steps, int64_t record_every, bool with_jac,
                   S* rec_states, S* rec_phi, const S* limits, int64_t* status, S* trace = nullptr,
                   PickLog* log = nullptr) {
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
      if (!with_jac) {
        substep<S>(w, state.data(), sc, nullptr);
        if (log != nullptr)
          for (int a = 0; a < n; ++a) {
            log->counts.push_back(static_cast<int32_t>(sc.picks[a].size()));
            for (const Pick& pk : sc.picks[a])
              log->picks.push_back(static_cast<uint32_t>(pk.shape) << 16 |
                                  (static_cast<uint32_t>(pk.sphere) & 0xFFFFu));
          }
        continue;
      }
      substep(w, state.data(), sc, sc.jac.data());
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
// grad_init = sum_t Phi_t^T grad_t, as lam <- J^T lam backwards through the substeps.
template <typename S>
void adjoint_candidate(const World<S>& w, const S* init, int64_t steps, int64_t record_every,
                       const S* rec_states, const S* trace, const S* grad, S* out,
                       const int32_t* counts = nullptr, const uint32_t* picks = nullptr, int64_t total = 0) {
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
      substep_adjoint(w, s, sc, lam.data());
    }
  }
  std::copy(lam.begin(), lam.end(), out);
}

// candidates 0..b-1 spread over threads, handed out one at a time (they differ in cost: contacts)
template <typename F>
void parallel_for(int64_t b, int64_t threads, F work) {
  const int64_t workers = std::min<int64_t>(std::max<int64_t>(threads, 1), b);
  if (workers <= 1) {
    for (int64_t i = 0; i < b; ++i) work(i);
    return;
  }
  std::atomic<int64_t> next{0};
  std::vector<std::thread> pool;
  std::exception_ptr error;
  std::mutex error_lock;
  for (int64_t t = 0; t < workers; ++t)
    pool.emplace_back([&] {
      try {
        for (int64_t i = next++; i < b; i = next++) work(i);
      } catch (...) {
        std::lock_guard<std::mutex> guard(error_lock);
        error = std::current_exception();
      }
    });
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
}

// Checks the World's arrays against schema.h (count, dtype, rank, sizes; the symbolic sizes N, S,
// K, P, G must agree across arrays), naming the field of the first mismatch.
inline void check_world(const std::vector<torch::Tensor>& t, const std::vector<double>& f,
                        const std::vector<int64_t>& iv, bool limits_allowed) {
  using namespace schema;
  TORCH_CHECK(static_cast<int>(t.size()) == WORLD_FIELD_COUNT, "native world: ", t.size(), " arrays, the schema has ",
              static_cast<int>(WORLD_FIELD_COUNT), " (dejaview/sim/native/schema.py and schema.h out of step?)");
  TORCH_CHECK(f.size() == FLOAT_COUNT || (limits_allowed && f.size() == FLOAT_COUNT + 2), "native world: ",
              f.size(), " floats, the schema has ", FLOAT_COUNT, limits_allowed ? " (+2 divergence limits)" : "");
  TORCH_CHECK(iv.size() == INT_COUNT, "native world: ", iv.size(), " ints, the schema has ", INT_COUNT);
  int64_t sizes[6] = {-1, -1, -1, -1, -1, SHAPE_WIDTH};  // N, S, K, P, G, F
  for (int i = 0; i < WORLD_FIELD_COUNT; ++i) {
    const FieldSpec& spec = WORLD_SPECS[i];
    const torch::Tensor& x = t[i];
    TORCH_CHECK(x.device().is_cpu() && x.scalar_type() == (spec.is_int ? torch::kInt64 : torch::kFloat64),
                "native world field '", spec.name, "': expected ", spec.is_int ? "int64" : "float64",
                " on the CPU, got ", x.scalar_type(), " on ", x.device());
    TORCH_CHECK(x.dim() == spec.ndim, "native world field '", spec.name, "': expected ", spec.ndim,
                " dimensions, got shape ", x.sizes());
    for (int d = 0; d < spec.ndim; ++d) {
      const int want = spec.dims[d];  // a size, or -1 - the index of a named dimension
      if (want < 0 && sizes[-want - 1] < 0) {  // the first array to name it sets it
        sizes[-want - 1] = x.size(d);
        continue;
      }
      const int64_t expected = want < 0 ? sizes[-want - 1] : want;
      TORCH_CHECK(x.size(d) == expected, "native world field '", spec.name, "': dimension ", d, " is ",
                  x.size(d), ", expected ", expected, " (shape ", x.sizes(), ")");
    }
  }
  TORCH_CHECK(iv[I_SUBSTEPS] >= 1 && iv[I_MAX_STATIC_CONTACTS] >= 1 && iv[I_MAX_PAIR_CONTACTS] >= 1,
              "native world: substeps and contact capacities must be >= 1");
}

template <typename S>
World<S> make_world(const std::vector<torch::Tensor>& t, const std::vector<double>& f, const std::vector<int64_t>& iv) {
  using namespace schema;  // the arrays, the shape row's columns, the scalars: schema.h
  World<S> w;
  w.n = static_cast<int>(t[MASS].size(0));
  w.s_max = static_cast<int>(t[CENTERS].size(1));
  w.k = static_cast<int>(t[SHAPES].size(0));
  w.p = static_cast<int>(t[PAIRS].size(0));
  w.mass = t[MASS].data_ptr<S>();
  w.inertia = t[INERTIA].data_ptr<S>();
  w.inv_inertia = t[INV_INERTIA].data_ptr<S>();
  w.centers = t[CENTERS].data_ptr<S>();
  w.radii = t[RADII].data_ptr<S>();
  w.bound = t[BOUND].data_ptr<S>();
  w.inv_i_min = t[INV_INERTIA_MIN].data_ptr<S>();
  const int64_t* counts = t[COUNTS].data_ptr<int64_t>();
  for (int i = 0; i < w.n; ++i) {
    TORCH_CHECK(counts[i] >= 0 && counts[i] <= w.s_max, "native world field 'counts': body ", i, " has ",
                counts[i], " spheres of at most ", w.s_max);
    w.count.push_back(static_cast<int>(counts[i]));
    S reach = 0;
    for (int j = 0; j < w.count[i]; ++j) {
      const S* c = w.centers + (static_cast<int64_t>(i) * w.s_max + j) * 3;
      reach = std::max(reach, std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]));
    }
    w.reach.push_back(reach);
  }
  w.mu_static = t[MU_STATIC].data_ptr<S>();
  w.unload_static = t[UNLOAD_STATIC].data_ptr<S>();
  w.pairs = t[PAIRS].data_ptr<int64_t>();
  w.mu_pair = t[MU_PAIR].data_ptr<S>();
  w.unload_pair = t[UNLOAD_PAIR].data_ptr<S>();
  w.mass_pair = t[MASS_PAIR].data_ptr<S>();
  w.box_half = t[BOX_HALF].data_ptr<S>();
  w.pair_surface = t[PAIR_SURFACE].data_ptr<int64_t>();
  for (int pi = 0; pi < w.p; ++pi)
    TORCH_CHECK(w.pair_surface[pi] >= -1 && w.pair_surface[pi] <= 1, "native world field 'pair_surface': pair ",
                pi, " has ", w.pair_surface[pi], " (schema: -1, 0 or 1)");
  for (int i = 0; i < w.n; ++i) {  // a box's surface and corner spheres reach its corners, beyond its spheres' centres
    const S* half = w.box_half + 3 * i;
    w.reach[i] = std::max(w.reach[i], std::sqrt(half[0] * half[0] + half[1] * half[1] + half[2] * half[2]));
  }
  const S* rows = t[SHAPES].data_ptr<S>();
  const S* grid = t[GRID].numel() ? t[GRID].data_ptr<S>() : nullptr;
  const int64_t grid_size = t[GRID].numel();
  for (int k = 0; k < w.k; ++k) {
    const S* r = rows + static_cast<int64_t>(SHAPE_WIDTH) * k;
    Shape<S> sh;
    sh.kind = static_cast<int>(r[SHAPE_KIND]);
    TORCH_CHECK(sh.kind >= 0 && sh.kind < KIND_COUNT, "native world field 'shapes': static ", k, " has kind ",
                r[SHAPE_KIND], " (schema: 0 to ", KIND_COUNT - 1, ")");
    for (int i = 0; i < 9; ++i) sh.rot[i] = r[SHAPE_ROTATION + i];
    for (int i = 0; i < 3; ++i) {
      sh.trans[i] = r[SHAPE_TRANSLATION + i];
      sh.half[i] = r[SHAPE_HALF + i];
      sh.origin[i] = r[SHAPE_GRID_ORIGIN + i];
    }
    sh.radius = r[SHAPE_RADIUS];
    sh.half_height = r[SHAPE_HALF_HEIGHT];
    sh.spacing = r[SHAPE_GRID_SPACING];
    sh.lipschitz = r[SHAPE_LIPSCHITZ];
    sh.nx = static_cast<int64_t>(r[SHAPE_GRID_SHAPE]);
    sh.ny = static_cast<int64_t>(r[SHAPE_GRID_SHAPE + 1]);
    sh.nz = static_cast<int64_t>(r[SHAPE_GRID_SHAPE + 2]);
    const int64_t offset = static_cast<int64_t>(r[SHAPE_GRID_OFFSET]);
    if (sh.kind == KIND_GRID)
      TORCH_CHECK(offset >= 0 && offset + sh.nx * sh.ny * sh.nz <= grid_size, "native world field 'grid': static ",
                  k, "'s samples run past its end");
    sh.grid = sh.kind == KIND_GRID ? grid + offset : nullptr;
    w.shapes.push_back(sh);
  }
  w.gravity[0] = static_cast<S>(f[F_GRAVITY_X]);
  w.gravity[1] = static_cast<S>(f[F_GRAVITY_Y]);
  w.gravity[2] = static_cast<S>(f[F_GRAVITY_Z]);
  w.h = static_cast<S>(f[F_SUBSTEP_DT]);
  w.omega = static_cast<S>(f[F_CONTACT_FREQUENCY]);
  w.unload_velocity = static_cast<S>(f[F_UNLOAD_VELOCITY]);
  w.substeps = static_cast<int>(iv[I_SUBSTEPS]);
  w.cap_static = static_cast<int>(iv[I_MAX_STATIC_CONTACTS]);
  w.cap_pair = static_cast<int>(iv[I_MAX_PAIR_CONTACTS]);
  return w;
}

}  // namespace dv

// threads: candidates are spread over this many threads (torch's intra-op pool is not used, so the
// simulator's parallelism does not depend on torch.set_num_threads).
// init: (B, N, 13) -> states (B, R, N, 13), extra and status (B, 4). mode 0: values only (extra
// empty); 1: extra = phi (B, R, 13N, 13N) = d state / d init (forward mode); 2: extra = the trace
// (B, steps * (substeps - k0), N, 13) of substep states that reverse mode (adjoint) reads, and three
// more outputs, the static picks of every substep (PickLog): counts (B, steps * substeps, N) int32,
// picks (total,) int32 (shape << 16 | sphere), starts (B + 1,) int64 (candidate i's picks are
// picks[starts[i]:starts[i + 1]]); all three empty where the scene's indices do not fit. status:
// where a candidate diverged (run_candidate), checked only when floats carries the limits
// {reach, speed} after the schema's FLOATS (mode 0 only).
std::vector<torch::Tensor> rollout(torch::Tensor init, int64_t steps, int64_t record_every, int64_t mode,
                                   std::vector<torch::Tensor> world, std::vector<double> floats,
                                   std::vector<int64_t> ints, int64_t threads) {
  TORCH_CHECK(init.device().is_cpu(), "the native simulator runs on the CPU");
  TORCH_CHECK(init.dim() == 3 && init.size(2) == dv::STATE_WIDTH, "init must be (B, N, 13)");
  TORCH_CHECK(steps >= 1 && record_every >= 1, "steps and record_every must be >= 1");
  TORCH_CHECK(mode >= 0 && mode <= 2, "mode must be 0 (values), 1 (Jacobians) or 2 (trace)");
  TORCH_CHECK(init.scalar_type() == torch::kFloat64, "the native simulator runs in float64");
  dv::check_world(world, floats, ints, mode == 0);  // the divergence limits (reach, speed) in values mode only
  init = init.contiguous();
  for (auto& t : world) t = t.contiguous();
  const int64_t b = init.size(0), n = init.size(1);
  const int64_t dim = dv::STATE_WIDTH * n;
  const int64_t records = (steps + record_every - 1) / record_every;
  const bool with_jac = mode == 1;
  const int64_t per_step = ints[dv::schema::I_SUBSTEPS] - dv::trace_first(record_every);
  auto states = torch::empty({b, records, n, dv::STATE_WIDTH}, init.options());
  torch::Tensor extra;
  if (mode == 1) extra = torch::empty({b, records, dim, dim}, init.options());
  else if (mode == 2) extra = torch::empty({b, steps * per_step, n, dv::STATE_WIDTH}, init.options());
  else extra = torch::empty({0}, init.options());
  auto status = torch::full({b, 4}, -1, init.options().dtype(torch::kInt64));
  std::vector<dv::PickLog> logs;
  {
    using S = double;
    const dv::World<S> w = dv::make_world<S>(world, floats, ints);
    TORCH_CHECK(w.n == n, "state and world disagree on the number of bodies");
    const S* in = init.data_ptr<S>();
    S* out = states.data_ptr<S>();
    S* ex = mode ? extra.data_ptr<S>() : nullptr;
    const int64_t ex_per = mode == 1 ? records * dim * dim : steps * per_step * dim;
    constexpr size_t nf = dv::schema::FLOAT_COUNT;
    const bool has_limits = floats.size() == nf + 2;
    const S limit_values[2] = {has_limits ? floats[nf] : S(0), has_limits ? floats[nf + 1] : S(0)};
    const S* limits = has_limits ? limit_values : nullptr;
    int64_t* st = status.data_ptr<int64_t>();
    pybind11::gil_scoped_release no_gil;  // other Python threads (a server's event loop) run meanwhile
    if (mode == 2 && dv::pick_log_fits(w)) logs.resize(b);
    dv::parallel_for(b, threads, [&](int64_t i) {
      dv::run_candidate<S>(w, in + i * dim, steps, record_every, with_jac, out + i * records * dim,
                           with_jac ? ex + i * ex_per : nullptr, limits, st + 4 * i,
                           mode == 2 ? ex + i * ex_per : nullptr, logs.empty() ? nullptr : &logs[i]);
    });
  }
  if (mode != 2) return {states, extra, status};
  const auto i32 = init.options().dtype(torch::kInt32), i64 = init.options().dtype(torch::kInt64);
  if (logs.empty()) return {states, extra, status, torch::empty({0}, i32), torch::empty({0}, i32),
                            torch::empty({0}, i64)};
  auto counts = torch::empty({b, steps * ints[dv::schema::I_SUBSTEPS], n}, i32);
  auto starts = torch::empty({b + 1}, i64);
  int64_t* at = starts.data_ptr<int64_t>();
  at[0] = 0;
  for (int64_t i = 0; i < b; ++i) at[i + 1] = at[i] + static_cast<int64_t>(logs[i].picks.size());
  auto picks = torch::empty({at[b]}, i32);
  for (int64_t i = 0; i < b; ++i) {  // each candidate's log freed once copied
    std::copy(logs[i].counts.begin(), logs[i].counts.end(), counts.data_ptr<int32_t>() + i * counts.size(1) * n);
    std::copy(logs[i].picks.begin(), logs[i].picks.end(), reinterpret_cast<uint32_t*>(picks.data_ptr<int32_t>()) + at[i]);
    logs[i] = dv::PickLog();
  }
  return {states, extra, status, counts, picks, starts};
}

// Reverse mode: grad (B, R, N, 13) of the records of rollout(init, ..., mode 2) (states, trace)
// -> grad init (B, N, 13) = sum_t Phi_t^T grad_t, without forming Phi.
// counts, picks, starts: the rollout's pick log (empty: select the contacts again).
torch::Tensor adjoint(torch::Tensor init, torch::Tensor states, torch::Tensor trace, torch::Tensor grad,
                      int64_t steps, int64_t record_every, std::vector<torch::Tensor> world,
                      std::vector<double> floats, std::vector<int64_t> ints, int64_t threads,
                      torch::Tensor counts, torch::Tensor picks, torch::Tensor starts) {
  TORCH_CHECK(init.dim() == 3 && init.size(2) == dv::STATE_WIDTH && init.scalar_type() == torch::kFloat64 &&
              init.device().is_cpu(), "init must be (B, N, 13) float64 on the CPU");
  init = init.contiguous();
  states = states.contiguous();
  trace = trace.contiguous();
  grad = grad.to(torch::kFloat64).contiguous();
  for (auto& t : world) t = t.contiguous();
  const int64_t b = init.size(0), n = init.size(1);
  const int64_t dim = dv::STATE_WIDTH * n;
  const int64_t records = (steps + record_every - 1) / record_every;
  dv::check_world(world, floats, ints, false);
  const int64_t per_step = ints[dv::schema::I_SUBSTEPS] - dv::trace_first(record_every);
  TORCH_CHECK(states.numel() == b * records * dim && grad.numel() == b * records * dim &&
              trace.numel() == b * steps * per_step * dim, "adjoint: states, trace or grad of the wrong size");
  const bool logged = starts.numel() > 0;
  if (logged) {
    counts = counts.contiguous();
    picks = picks.contiguous();
    starts = starts.contiguous();
    TORCH_CHECK(counts.scalar_type() == torch::kInt32 && picks.scalar_type() == torch::kInt32 &&
                starts.scalar_type() == torch::kInt64 && counts.numel() == b * steps * ints[dv::schema::I_SUBSTEPS] * n &&
                starts.numel() == b + 1 && starts[b].item<int64_t>() == picks.numel(),
                "adjoint: the pick log does not match the rollout");
  }
  auto out = torch::empty({b, n, dv::STATE_WIDTH}, init.options());
  {
    using S = double;
    const dv::World<S> w = dv::make_world<S>(world, floats, ints);
    TORCH_CHECK(w.n == n, "state and world disagree on the number of bodies");
    const int32_t* cn = logged ? counts.data_ptr<int32_t>() : nullptr;
    const uint32_t* pk = logged ? reinterpret_cast<const uint32_t*>(picks.data_ptr<int32_t>()) : nullptr;
    const int64_t* at = logged ? starts.data_ptr<int64_t>() : nullptr;
    const int64_t per_candidate = steps * w.substeps * n;
    const S* in = init.data_ptr<S>();
    const S* rs = states.data_ptr<S>();
    const S* tr = trace.data_ptr<S>();
    const S* g = grad.data_ptr<S>();
    S* o = out.data_ptr<S>();
    pybind11::gil_scoped_release no_gil;
    dv::parallel_for(b, threads, [&](int64_t i) {
      dv::adjoint_candidate<S>(w, in + i * dim, steps, record_every, rs + i * records * dim,
                               tr + i * steps * per_step * dim, g + i * records * dim, o + i * dim,
                               logged ? cn + i * per_candidate : nullptr, logged ? pk + at[i] : nullptr,
                               logged ? at[i + 1] - at[i] : 0);
    });
  }
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rollout", &rollout, "sphere-packing rollout with optional state Jacobians or trace (dejaview.sim.native)");
  m.def("adjoint", &adjoint, "reverse-mode gradient of a traced rollout (dejaview.sim.native)");
}
