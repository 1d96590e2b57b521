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
// with s = (x, q, v, w) (13 numbers: schema.h's STATE_*) and W = (F, tau). Forward mode: the rollout carries the
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
#include <optional>
#include <thread>
#include <cstdint>
#include <vector>

#include "step.h"        // one substep: selection, the step and its Jacobian, its adjoint
#include "recording.h"   // one candidate's rollout and records, its adjoint
#include "read_world.h"  // the World's arrays, checked against schema.h
#include "schema.h"

namespace dv {

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

// the rows of a (B, 3) float64 CPU tensor of physics (rollout's `physics`), or null where it is empty
inline const double* physics_of(std::optional<torch::Tensor>& given, int64_t b) {
  if (!given.has_value() || !given->defined() || given->numel() == 0) return nullptr;
  torch::Tensor& physics = *given;
  TORCH_CHECK(physics.scalar_type() == torch::kFloat64 && physics.device().is_cpu() && physics.dim() == 2 &&
              physics.size(0) == b && physics.size(1) == 3, "physics must be (B, 3) float64 on the CPU");
  physics = physics.contiguous();
  return physics.data_ptr<double>();
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
// {reach, speed} after the schema's FLOATS (mode 0 only). physics: (B, 3) float64, each candidate's
// logs of its friction, unloading and stiffness factors (World::mu_scale, ...), or empty (none).
std::vector<torch::Tensor> rollout(torch::Tensor init, int64_t steps, int64_t record_every, int64_t mode,
                                   std::vector<torch::Tensor> world, std::vector<double> floats,
                                   std::vector<int64_t> ints, int64_t threads, std::optional<torch::Tensor> physics) {
  TORCH_CHECK(init.device().is_cpu(), "the native simulator runs on the CPU");
  TORCH_CHECK(init.dim() == 3 && init.size(2) == dv::STATE_WIDTH, "init must be (B, N, 13)");
  TORCH_CHECK(steps >= 1 && record_every >= 1, "steps and record_every must be >= 1");
  TORCH_CHECK(mode >= 0 && mode <= 2, "mode must be 0 (values), 1 (Jacobians) or 2 (trace)");
  TORCH_CHECK(init.scalar_type() == torch::kFloat64, "the native simulator runs in float64");
  dv::check_world(world, floats, ints, mode == 0);  // the divergence limits (reach, speed) in values mode only
  init = init.contiguous();
  for (auto& t : world) t = t.contiguous();
  const int64_t b = init.size(0), n = init.size(1);
  const double* ph = dv::physics_of(physics, b);
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
      const dv::World<S> wp = ph ? dv::with_physics(w, ph + 3 * i) : dv::World<S>();
      dv::run_candidate<S>(ph ? wp : w, in + i * dim, steps, record_every, with_jac, out + i * records * dim,
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
// -> {grad init (B, N, 13) = sum_t Phi_t^T grad_t, without forming Phi; grad physics (B, 3), the
// gradient with respect to the rollout's physics (empty where it had none)}.
// counts, picks, starts: the rollout's pick log (empty: select the contacts again).
std::vector<torch::Tensor> adjoint(torch::Tensor init, torch::Tensor states, torch::Tensor trace, torch::Tensor grad,
                                   int64_t steps, int64_t record_every, std::vector<torch::Tensor> world,
                                   std::vector<double> floats, std::vector<int64_t> ints, int64_t threads,
                                   torch::Tensor counts, torch::Tensor picks, torch::Tensor starts,
                                   std::optional<torch::Tensor> physics) {
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
  const double* ph = dv::physics_of(physics, b);
  auto out_phys = ph ? torch::empty({b, 3}, init.options()) : torch::empty({0}, init.options());
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
    S* op = ph ? out_phys.data_ptr<S>() : nullptr;
    dv::parallel_for(b, threads, [&](int64_t i) {
      const dv::World<S> wp = ph ? dv::with_physics(w, ph + 3 * i) : dv::World<S>();
      dv::adjoint_candidate<S>(ph ? wp : w, in + i * dim, steps, record_every, rs + i * records * dim,
                               tr + i * steps * per_step * dim, g + i * records * dim, o + i * dim,
                               logged ? cn + i * per_candidate : nullptr, logged ? pk + at[i] : nullptr,
                               logged ? at[i + 1] - at[i] : 0, ph ? op + 3 * i : nullptr);
    });
  }
  return {out, out_phys};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  namespace py = pybind11;
  m.def("rollout", &rollout, "sphere-packing rollout with optional state Jacobians or trace (dejaview.sim.native)",
        py::arg("init"), py::arg("steps"), py::arg("record_every"), py::arg("mode"), py::arg("world"),
        py::arg("floats"), py::arg("ints"), py::arg("threads"), py::arg("physics") = py::none());
  m.def("adjoint", &adjoint, "reverse-mode gradient of a traced rollout (dejaview.sim.native)",
        py::arg("init"), py::arg("states"), py::arg("trace"), py::arg("grad"), py::arg("steps"),
        py::arg("record_every"), py::arg("world"), py::arg("floats"), py::arg("ints"), py::arg("threads"),
        py::arg("counts"), py::arg("picks"), py::arg("starts"), py::arg("physics") = py::none());
}
