// One substep of one candidate: contact selection (select_contacts), the step with or without its
// Jacobian (substep) and its adjoint (substep_adjoint), on a candidate's scratch (dejaview.sim.native;
// rollout.cpp's opening comment has the whole scheme).
#pragma once

#include <algorithm>
#include <cstdint>
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
  std::vector<S> next;                            // (N, STATE_WIDTH)
  std::vector<S> jac, dws;                        // substep Jacobian (13N)^2, dW/ds (6N x 13N)
  std::vector<S> key;                             // (N, K, s_max) clearance bounds (select_static)
  std::vector<S> floor, keymin;                   // (N, K) ... of every sphere, the smallest key
  std::vector<S> last;                            // (N, 12) position and rotation at the last selection
  std::vector<char> blk;                          // (N, N) nonzero state-row blocks of the Jacobian
  std::vector<StaticAdjoint<S>> static_adj;       // (N) static contacts' values for the way back
  std::vector<PairAdjoint<S>> pair_adj;           // (P) ... body pairs'
  std::vector<S> move;                            // (N) how far a sphere, corner or box surface point of each
                                                  // body moved this substep (World::reach)
  std::vector<S> travel;                          // (N) the sum of move over the substeps
  std::vector<char> placed;                       // (N) selected before (last holds its pose)
  std::vector<S> pair_clear;                      // (P) clearance bound of each pair (select_pair)
  const int32_t* logged = nullptr;                // (N) picks of this substep per body (PickLog), or null
  const uint32_t* logged_picks = nullptr;         // ... and the picks themselves, body after body
  S gphys[3] = {S(0), S(0), S(0)};                // reverse mode: the physics' gradient so far (World's factors' logs)
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
    S dx = 0, dr = 0;  // (indexed in place: through a pointer, g++ rounds the Jacobians differently)
    for (int i = 0; i < 3; ++i) dx += (state[STATE_WIDTH * a + STATE_POSITION + i] - last[i]) *
                                       (state[STATE_WIDTH * a + STATE_POSITION + i] - last[i]);
    for (int i = 0; i < 9; ++i) dr += (rot[i] - last[3 + i]) * (rot[i] - last[3 + i]);
    // |p_i' - p_i| <= |x' - x| + |R' - R|_F |c_i|
    // (no previous selection: every bound is -inf, nothing to lower)
    const S move = sc.placed[a] ? std::sqrt(dx) + std::sqrt(dr) * w.reach[a] : S(0);
    sc.placed[a] = 1;
    for (int i = 0; i < 3; ++i) last[i] = state[STATE_WIDTH * a + STATE_POSITION + i];
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
    sc.static_adj[a].backward(w, a, &mu[6 * a], &sc.next[STATE_WIDTH * a], sc.gphys);
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
                             &sc.next[STATE_WIDTH * b], sc.gphys);
  }
  std::copy(sc.next.begin(), sc.next.end(), lam);
}

}  // namespace dv
