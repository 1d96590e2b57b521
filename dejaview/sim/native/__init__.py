"""Native (C++) rollouts of the sphere-packing simulator, with exact state Jacobians.

The same model as ``dejaview.sim.contacts`` and ``dejaview.sim.integrate``,
written once in C++ (``rollout.cpp`` with ``dual.h``, ``contacts.h``,
``integrate.h``, ``adjoint.h``, ``step.h``, ``recording.h`` and the files they include, listed in
``docs/engines.md``; what it reads is ``dejaview.sim.native.schema``, by name through the
generated ``schema.h``) as templates over the number type:
plain doubles for values and forward-mode dual numbers for derivatives. Each
substep's Jacobian comes from three small dual passes per body (static
contacts with 13 tangents, a touching body pair with 26, the integration with
19), whatever the number of spheres. Gradients (``native_rollout``, a
``torch.autograd.Function``):

- reverse mode (autograd alone): the rollout keeps its substep states (a
  trace, O(steps * substeps * N)), and ``backward`` runs the adjoint
  ``lam <- J^T lam`` back through them by hand-written vector-Jacobian
  products of the same three pieces (``adjoint.h``; the dual passes are
  their reference), without forming any Jacobian; bodies the adjoint has
  not reached through contacts cost nothing there (``_Traced``);
- forward mode (``torch.func.jvp``/``jacfwd``, vmap included, or any
  ``torch.func`` transform): the rollout carries the product of the substep
  Jacobians ``Phi_t = d state_t / d state_0`` (13N x 13N) to every record and
  the tangent is ``Phi_t v`` (``_Rollout``; memory O(steps * (13N)^2)).
  ``DEJAVIEW_NATIVE_GRADIENT=phi`` sends reverse mode this way too
  (``sum_t Phi_t^T g_t``), for comparisons; a caller that
  takes many reverse passes of the same rollouts asks for it with
  ``preferring("phi")`` (``Posterior.jacobian`` under model uncertainty).

Both give the same gradients to round-off (``tests/sim/test_native_gradients.py``),
with no autograd graph of the rollout (no checkpointing needed). Without
gradients no Jacobian or trace is computed.

Contact selection is made on values, as ``dejaview.sim.contacts``' ``topk``
on detached depths. Spheres that do not touch carry exactly zero force and
zero derivative, so they are skipped; a body whose centre of mass is farther
from a static shape than ``L * bound`` (its bounding radius times the shape's
Lipschitz bound: 1 for analytic shapes, from the samples for grids) skips the
shape altogether. Results equal the torch simulator's up to the order of
floating-point sums (``tests/sim/test_native.py``).

Limits: float64 on the CPU; the body pair broad phase is per candidate. The
extension is compiled by ``scripts/setup`` or on first use (g++, about a
minute) into a folder of this install named after a hash of the source,
torch, Python and the compiler flags (``dejaview.sim.native.loader``: a build
killed half-way never blocks the next one).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import os
import threading
import warnings
import weakref
from pathlib import Path

import torch

from dejaview.errors import SimulationError
from dejaview.sim.native import schema
from dejaview.sim.state import STATE_WIDTH, State

SOURCE = Path(__file__).with_name("rollout.cpp")

ENGINES = ("auto", "native", "torch")
"""``auto``: native where it applies (float64 on the CPU, the extension builds), else torch."""

_LOCK = threading.Lock()
_EXTENSION = None
_BUILD_ERROR: SimulationError | None = None


def threads() -> int:
    """Threads a batched native rollout spreads its candidates over.

    ``DEJAVIEW_NATIVE_THREADS``, default every core (``os.cpu_count()``); independent of
    ``torch.set_num_threads`` (the CLI keeps torch's own ops on one thread).
    """
    value = os.environ.get("DEJAVIEW_NATIVE_THREADS")
    if value:
        try:
            return max(1, int(value))
        except ValueError:
            raise SimulationError(f"DEJAVIEW_NATIVE_THREADS must be an integer, got {value!r}") from None
    return _cpu_count()


@functools.lru_cache(maxsize=1)
def _cpu_count() -> int:
    """``os.cpu_count()``, read once (it costs ~20 us, a percent of a small rollout)."""
    return os.cpu_count() or 1


CFLAGS = ["-O3", "-march=native", "-fno-math-errno"]


def extension():
    """The compiled C++ module (built on first call, then loaded from this install's build folder).

    Raises:
        SimulationError: the build failed (no compiler, another process's build did not finish
            in time, ...); remembered for the process.
    """
    global _EXTENSION, _BUILD_ERROR
    with _LOCK:
        if _BUILD_ERROR is not None:
            raise _BUILD_ERROR
        if _EXTENSION is None:
            from dejaview.sim.native.loader import load_extension

            try:
                _EXTENSION = load_extension("dejaview_native", SOURCE, CFLAGS)
            except SimulationError as exc:
                _BUILD_ERROR = exc
                raise
            except Exception as exc:  # no compiler, a broken build
                lines = str(exc).strip().splitlines() or ["unknown error"]
                first = next((ln for ln in lines if "error" in ln.lower()), lines[-1])
                _BUILD_ERROR = SimulationError(f"the native simulator could not be built from "
                                               f"{SOURCE}: {first.strip()[:300]}")
                raise _BUILD_ERROR from exc
    return _EXTENSION


def available() -> bool:
    """True when the extension builds (or is built) on this machine."""
    try:
        extension()
    except SimulationError:
        return False
    return True


_WARNED = False


def use_native(engine: str, world) -> bool:
    """Whether a rollout of ``world`` runs natively under ``engine`` (one of ``ENGINES``).

    Raises:
        SimulationError: unknown engine, or ``native`` asked where it cannot run.
    """
    global _WARNED
    if engine == "torch":
        return False
    if engine not in ENGINES:
        raise SimulationError(f"unknown simulation engine {engine!r}; choose one of {', '.join(ENGINES)}")
    fits = world.dtype == torch.float64 and world.device.type == "cpu"
    if engine == "native":
        if not fits:
            raise SimulationError("the native engine runs in float64 on the CPU; this world is "
                                  f"{world.dtype} on {world.device} (use engine torch)")
        extension()
        return True
    if not fits:
        return False
    if available():
        return True
    if not _WARNED:
        _WARNED = True
        warnings.warn(f"{_BUILD_ERROR}; simulating with the torch engine", RuntimeWarning, stacklevel=2)
    return False


_PACKED: dict = {}


def pack_world(world) -> tuple[list[torch.Tensor], list[float], list[int]]:
    """The World as the flat arrays ``rollout.cpp`` reads.

    Cached while the World lives (weakly: a server builds a World per job, and a cache that
    kept them would grow with every job).
    """
    key = id(world)
    hit = _PACKED.get(key)
    if hit is not None and hit[0]() is world:
        return hit[1]
    # plain tensors even when first called under torch.func transforms (which would wrap them
    # at their level, and the cached copies would die with the transform)
    with torch._C._DisableFuncTorch(), torch.no_grad():
        packed = _pack(world)
    _PACKED[key] = (weakref.ref(world), packed)
    weakref.finalize(world, _PACKED.pop, key, None)
    return packed


def _pack(world) -> tuple[list[torch.Tensor], list[float], list[int]]:
    if world.dtype != torch.float64 or world.device.type != "cpu":
        raise SimulationError("the native simulator runs in float64 on the CPU; this world is "
                              f"{world.dtype} on {world.device}")
    return schema.pack(world)


class _Rollout(torch.autograd.Function):
    """init (B, N, 13) -> recorded states (B, R, N, 13), Jacobians (B, R, 13N, 13N)."""

    @staticmethod
    def forward(init, steps, record_every, with_jac, packed, physics=None):
        tensors, floats, ints = packed
        states, phi, _ = extension().rollout(init.detach().contiguous(), steps, record_every,
                                             1 if with_jac else 0, tensors, floats, ints, threads(),
                                             _plain(physics))
        return states, phi

    @staticmethod
    def setup_context(ctx, inputs, output):
        _, phi = output
        ctx.mark_non_differentiable(phi)
        ctx.with_jac = inputs[3]
        ctx.save_for_backward(phi)
        ctx.save_for_forward(phi)

    @staticmethod
    def backward(ctx, grad_states, _grad_phi):
        if not ctx.with_jac:
            raise SimulationError("native rollout: a gradient was asked of a rollout run without "
                                  "Jacobians")
        (phi,) = ctx.saved_tensors
        b, r, n, _ = grad_states.shape
        g = torch.einsum("brij,bri->bj", phi, grad_states.reshape(b, r, STATE_WIDTH * n))
        return g.reshape(b, n, STATE_WIDTH), None, None, None, None, None

    @staticmethod
    def jvp(ctx, tangent, *_):
        if not ctx.with_jac:
            raise SimulationError("native rollout: a tangent was pushed through a rollout run "
                                  "without Jacobians")
        (phi,) = ctx.saved_tensors
        b, r, dim, _ = phi.shape
        out = torch.einsum("brij,bj->bri", phi, tangent.reshape(b, dim))
        return out.reshape(b, r, dim // STATE_WIDTH, STATE_WIDTH), None

    @staticmethod
    def vmap(info, in_dims, init, steps, record_every, with_jac, packed, physics=None):
        dim = in_dims[0]
        if physics is not None and in_dims[5] is not None:
            raise SimulationError("native rollout: physics cannot be batched by vmap")
        if dim is None:
            return _Rollout.apply(init, steps, record_every, with_jac, packed, physics), (None, None)
        x = init.movedim(dim, 0)
        v, b = x.shape[:2]
        ph = None if physics is None else physics.repeat(v, 1)
        states, phi = _Rollout.apply(x.reshape(v * b, *x.shape[2:]), steps, record_every, with_jac,
                                     packed, ph)
        return (states.reshape(v, b, *states.shape[1:]), phi.reshape(v, b, *phi.shape[1:])), (0, 0)


class _Traced(torch.autograd.Function):
    """init (B, N, 13) -> recorded states (B, R, N, 13), reverse mode by the adjoint.

    The rollout keeps its substep states (the trace, (B, steps * substeps, N, 13) at most);
    ``backward`` runs ``lam <- J^T lam`` back through them in C++ (``adjoint`` in
    ``rollout.cpp``), from the same per-substep dual passes as the Jacobians of ``_Rollout``,
    without forming them: memory O(steps * substeps * N) and no (13N)^2 products. The rollout
    also logs which spheres touched which static shape at each substep (4 bytes a contact), so
    the way back reads them instead of selecting the contacts again (0.7 of the N = 1 box's
    3.2 ms adjoint; the same picks, bit for bit).
    """

    # forward(ctx, ...) rather than forward + setup_context: with setup_context every apply binds
    # the arguments through inspect.signature (~0.1 ms a call); this Function never runs under
    # torch.func transforms (``_reverse_only``), which are what setup_context is for
    @staticmethod
    def forward(ctx, init, steps, record_every, packed, physics=None):
        tensors, floats, ints = packed
        plain = _plain(physics)
        states, trace, _, *log = extension().rollout(init.detach().contiguous(), steps, record_every, 2,
                                                     tensors, floats, ints, threads(), plain)
        ctx.mark_non_differentiable(trace)
        ctx.steps, ctx.record_every, ctx.packed = steps, record_every, packed
        ctx.save_for_backward(init.detach(), states, trace, plain, *log)
        return states, trace

    @staticmethod
    def backward(ctx, grad_states, _grad_trace):
        init, states, trace, plain, *log = ctx.saved_tensors
        tensors, floats, ints = ctx.packed
        g, g_phys = extension().adjoint(init, states, trace, grad_states, ctx.steps, ctx.record_every,
                                        tensors, floats, ints, threads(), *log, plain)
        return g, None, None, None, (g_phys if g_phys.numel() else None)


GRADIENTS = ("adjoint", "phi")
"""How a native rollout differentiates (``DEJAVIEW_NATIVE_GRADIENT``): ``adjoint`` (default)
runs reverse mode by the adjoint wherever only autograd asks for a gradient; ``phi`` carries
the full state Jacobians (``_Rollout``) for reverse mode too (kept for comparisons). Forward mode and ``torch.func`` transforms always use the Jacobians."""


_PREFERRED = contextvars.ContextVar("dejaview_native_gradient", default="adjoint")


@contextlib.contextmanager
def preferring(path: str):
    """Native rollouts made in this block differentiate in reverse mode by ``path``
    (``GRADIENTS``) unless ``DEJAVIEW_NATIVE_GRADIENT`` names one. For a caller that takes many
    reverse passes of the same rollouts, a Jacobian row by row (``Posterior.jacobian``): each
    ``adjoint`` pass runs back through the whole trace, each ``phi`` pass is a product with the
    Jacobians the rollout carried (13N wide, paid once)."""
    if path not in GRADIENTS:
        raise ValueError(f"gradient path must be one of {', '.join(GRADIENTS)}, got {path!r}")
    token = _PREFERRED.set(path)
    try:
        yield
    finally:
        _PREFERRED.reset(token)


def gradient_path() -> str:
    """``DEJAVIEW_NATIVE_GRADIENT`` (``GRADIENTS``), else the block's ``preferring``, else
    ``adjoint``."""
    value = os.environ.get("DEJAVIEW_NATIVE_GRADIENT") or _PREFERRED.get()
    if value not in GRADIENTS:
        raise SimulationError(f"DEJAVIEW_NATIVE_GRADIENT must be one of {', '.join(GRADIENTS)}, "
                              f"got {value!r}")
    return value


def _reverse_only(init: torch.Tensor) -> bool:
    """True when only autograd's reverse mode can ask this rollout for a gradient."""
    import torch._C._functorch as ft

    return (ft.peek_interpreter_stack() is None
            and torch.autograd.forward_ad.unpack_dual(init).tangent is None)


def _needs_jacobian(init: torch.Tensor) -> bool:
    """Whether a derivative may be asked of a rollout through ``init`` (the start, or the physics)."""
    import torch._C._functorch as ft

    if ft.peek_interpreter_stack() is not None:  # torch.func transforms (jvp, vmap, grad)
        return True
    if torch.is_grad_enabled() and init.requires_grad:
        return True
    return torch.autograd.forward_ad.unpack_dual(init).tangent is not None


def native_rollout(world, state: State, steps: int, record_every: int = 1, *,
                   check_divergence: bool = False, first_step: int = 0, physics: torch.Tensor | None = None):
    """``dejaview.sim.integrate.rollout`` on the native simulator.

    Args:
        world: the World (float64, CPU).
        state: initial State (B, N, ...).
        steps: number of steps (>= 1).
        record_every: record interval; the initial and final states are always recorded.
        check_divergence: forward simulation: end with the error of ``dejaview.sim.divergence``
            when a state turns non-finite or out of range (no gradients then). Off, a diverged
            candidate of a batch just carries its NaN or inf to its loss.
        first_step: number of the first step (simulations run in chunks): for the error, and where a
            moving robot's links start (``dejaview.sim.motion``).
        physics: optional (B, 3) float64, each candidate's physics as the logs of factors on every
            pair's friction, unloading factor (capped at 1) and the contact stiffness
            (``dejaview.sim.physics``); differentiable in reverse mode.
    Returns:
        Trajectory with T = 1 + ceil(steps / record_every) records, differentiable with
        respect to ``state`` in reverse and forward mode, and to ``physics`` in reverse mode.
    Raises:
        SimulationError: with ``check_divergence``, naming the object, the step and the quantity;
            a forward-mode tangent of ``physics`` (reverse mode only).
    """
    from dejaview.sim.state import Trajectory

    packed = pack_world(world)
    if first_step and world.moving:  # the moving statics stand where step first_step finds them
        tensors, floats, ints = packed
        ints = list(ints)
        ints[schema.INTS.index("first_substep")] = int(first_step) * world.substeps
        packed = (tensors, floats, ints)
    if state.position.dtype != torch.float64 or state.position.device.type != "cpu":
        raise SimulationError("the native simulator runs in float64 on the CPU; the state is "
                              f"{state.position.dtype} on {state.position.device}")
    init = state.flat()  # (B, N, STATE_WIDTH)
    physics_grad = physics is not None and _needs_jacobian(physics)
    if check_divergence:
        from dejaview.sim import divergence

        tensors, floats, ints = packed
        states, _, status = extension().rollout(init.detach().contiguous(), int(steps), int(record_every),
                                                0, tensors, floats + divergence.native_limits(), ints,
                                                threads(), _plain(physics))
        bad = (status[:, 0] >= 0).nonzero()
        if bad.numel():
            b = int(bad[0, 0])
            step, body, quantity, record = (int(v) for v in status[b])
            raise divergence.describe(world, first_step + step, body, quantity, states[b, record, body])
    elif not (_needs_jacobian(init) or physics_grad):  # values only: no autograd.Function to pass through
        tensors, floats, ints = packed
        states, _, _ = extension().rollout(init.detach().contiguous(), int(steps), int(record_every), 0,
                                           tensors, floats, ints, threads(), _plain(physics))
    elif physics_grad or (_reverse_only(init) and gradient_path() == "adjoint"):
        if not _reverse_only(init):
            raise SimulationError("native rollout: derivatives with respect to the physics are "
                                  "taken in reverse mode only (no forward mode or torch.func)")
        states, _ = _Traced.apply(init, int(steps), int(record_every), packed, physics)
    else:
        states, _ = _Rollout.apply(init, int(steps), int(record_every), True, packed, physics)
    seq = torch.cat([init.unsqueeze(0), states.transpose(0, 1)], 0)  # (T, B, N, STATE_WIDTH)
    return Trajectory(State.from_flat(seq),
                      record_steps(steps, record_every), world.dt)


def _plain(physics: torch.Tensor | None) -> torch.Tensor:
    """``physics`` (B, 3) as the extension reads it (float64, contiguous, no autograd), or an empty
    tensor for none."""
    if physics is None:
        return torch.empty(0, dtype=torch.float64)
    return physics.detach().to(torch.float64).contiguous()


def record_steps(steps: int, record_every: int) -> torch.Tensor:
    """(R + 1,) step numbers of a rollout's records: 0, the multiples of ``record_every``, ``steps``."""
    recorded = torch.arange(0, steps + 1, record_every)
    if steps % record_every:
        recorded = torch.cat([recorded, torch.tensor([steps])])
    return recorded
