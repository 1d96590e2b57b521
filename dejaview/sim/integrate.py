"""Time integration: ``step(world, state) -> state`` and rollouts.

Each step of length ``world.dt`` runs ``world.substeps`` substeps of
semi-implicit (symplectic) Euler, h = dt / substeps:

    F, tau  = gravity + contact forces (dejaview.sim.contacts) at (x, q, v, w)
    v'      = v + h F / m
    w'      = w + h I_w^-1 (tau - w x (I_w w)),   I_w = R I_body R^T   (gyroscopic term)
    x'      = x + h v'
    q'      = normalise(exp(h w' / 2) * q)

A rollout is a Python loop over ``step``; differentiation (autograd,
``torch.func.jvp``/``jacfwd``), batching and compilation wrap it from outside.
Reverse-mode memory can be bounded with activation checkpointing over chunks
of steps (``checkpoint_every``).

``rollout(..., engine="native")`` runs the same model in C++
(``dejaview.sim.native``): states equal to round-off, exact forward- and
reverse-mode gradients through a custom autograd Function, orders of
magnitude faster than eager (``docs/benchmarks.md``, "Simulator");
``engine="auto"`` picks it wherever it
applies (float64 on the CPU). ``rollout`` itself defaults to this module
(``engine="torch"``), the reference the native code is tested against;
``SpheresProblem``, ``simulate`` and the CLI default to ``auto``.

``rollout(..., compile=True)`` runs chunks of steps through ``torch.compile``
(one graph per World, chunk length, batch shape and grad mode, kept for the
life of the process; inductor also caches generated code on disk). A
compiled chunk runs several times faster than eager, but its first compile
takes minutes (``docs/benchmarks.md``), so eager stays the default; compile
pays off for long optimisations, heatmaps and benchmarks.
"""

from __future__ import annotations

import types
from dataclasses import replace

import torch
from torch.utils.checkpoint import checkpoint

from dejaview.errors import SimulationError
from dejaview.scene import bounds
from dejaview.sim import contacts
from dejaview.sim.rotation import integrate_quat, quat_to_matrix, small_matmul
from dejaview.sim.state import State, Trajectory  # noqa: F401  (Trajectory re-exported)
from dejaview.sim.world import World


def _transforms_active() -> bool:
    """True under torch.func transforms or torch.compile (no data-dependent branches then)."""
    import torch._C._functorch as ft

    return ft.peek_interpreter_stack() is not None or torch.compiler.is_compiling()


def wrench(world: World, state: State, h: float, broadphase: bool | None = None):
    """Total force and torque (gravity and contacts) on every body.

    Args:
        world: the World.
        state: State (B, N, ...).
        h: integration substep (s).
        broadphase: skip body pairs whose bounding spheres are apart (a data-
            dependent branch; default: on in eager mode, off under transforms).
    Returns:
        force (B, N, 3), torque (B, N, 3), rotation matrices (B, N, 3, 3),
        world-frame inverse inertia (B, N, 3, 3).
    """
    rot = quat_to_matrix(state.orientation)  # (B, N, 3, 3)
    rot_t = rot.transpose(-1, -2)
    spheres = state.position.unsqueeze(-2) + small_matmul(world.centers, rot_t)
    inv_w = small_matmul(small_matmul(rot, world.inv_inertia), rot_t)
    force, torque = contacts.static_contact_wrench(world, state, spheres, h, inv_w, rot)
    if world.pairs.shape[0] > 0:
        if broadphase is None:
            broadphase = not _transforms_active()
        ids = None
        if broadphase:
            ids = contacts.pair_bounding_overlap(world, state).nonzero().flatten()
        if ids is None or ids.numel() > 0:
            f2, t2 = contacts.pair_contact_wrench(world, state, spheres, h, inv_w, ids)
            force = force + f2
            torque = torque + t2
    force = force + world.mass[:, None] * world.gravity
    return force, torque, rot, inv_w


def substep(world: World, state: State, h: float, broadphase: bool | None = None) -> State:
    """One semi-implicit Euler substep of length ``h``."""
    force, torque, rot, inv_w = wrench(world, state, h, broadphase)
    v = state.linear_velocity + (h / world.mass)[:, None] * force
    w = state.angular_velocity
    inertia_w = small_matmul(small_matmul(rot, world.inertia), rot.transpose(-1, -2))  # (B, N, 3, 3)
    lw = small_matmul(inertia_w, w.unsqueeze(-1)).squeeze(-1)
    gyro = torch.linalg.cross(w, lw, dim=-1)
    w = w + h * small_matmul(inv_w, (torque - gyro).unsqueeze(-1)).squeeze(-1)
    x = state.position + h * v
    q = integrate_quat(state.orientation, w, h)
    return State(x, q, v, w)


def step(world: World, state: State, broadphase: bool | None = None, index: int = 0) -> State:
    """Advance ``state`` by one step ``world.dt`` (``world.substeps`` substeps).

    Args:
        world: the World.
        state: State with batch dimension B.
        index: which step of a rollout from time 0 this is (0 the first): where a moving robot's
            links are (``World.posed``); nothing else depends on it.
    Returns:
        the State after dt.
    """
    h = world.dt / world.substeps
    for k in range(world.substeps):
        state = substep(world.posed(index * world.substeps + k), state, h, broadphase)
    return state


_COMPILED: dict = {}


def compiled_chunk(world: World, steps: int):
    """``torch.compile``d function advancing a state by ``steps`` steps of ``world``.

    The function takes and returns the four State tensors; a world with moving statics (a moving
    robot's links) also takes ``posed``, the ``steps * substeps`` Worlds of the chunk's substeps
    (``World.posed``): their statics' tensors are inputs of the graph, not constants, so the
    chunks of a rollout share their compile. Compiled once per (world, steps) and cached for
    the process (the world is kept alive by the cache).
    """
    key = (id(world), steps)
    if key not in _COMPILED:
        h = world.dt / world.substeps

        def chunk(position, orientation, linear_velocity, angular_velocity, posed=()):
            s = State(position, orientation, linear_velocity, angular_velocity)
            out = []
            for i in range(steps):
                if posed:
                    for k in range(world.substeps):
                        s = substep(posed[i * world.substeps + k], s, h, False)
                else:
                    s = step(world, s, broadphase=False)
                out.extend(s.tensors())
            return tuple(out)

        # a code object of its own per (world, steps): dynamo keeps its cache, and its limit of
        # ``torch._dynamo.config.recompile_limit`` (8) recompiles, per code object, and each World
        # is a recompile of the same closure; a process compiling for a ninth World (a recovery
        # suite, a long-lived worker) would otherwise fall back to eager without a word
        chunk = types.FunctionType(chunk.__code__.replace(), chunk.__globals__, chunk.__name__,
                                   chunk.__defaults__, chunk.__closure__)
        _COMPILED[key] = (world, torch.compile(chunk, dynamic=False, fullgraph=True))
    return _COMPILED[key][1]


def rollout(world: World, state: State, steps: int | None = None, record_every: int = 1,
            checkpoint_every: int | None = None, step_fn=None,
            broadphase: bool | None = None, compile: bool = False,
            compile_chunk: int = 5, engine: str = "torch", max_steps: int | None = None,
            physics: torch.Tensor | None = None) -> Trajectory:
    """Simulate ``steps`` steps from ``state`` and record every ``record_every``-th state.

    Args:
        world: the World.
        state: initial State (B, N, ...).
        steps: number of steps (default ``world.steps``).
        record_every: record interval in steps; the initial and the final state
            are always recorded.
        checkpoint_every: if set, run chunks of this many steps under
            ``torch.utils.checkpoint`` so reverse mode stores only chunk
            boundaries (memory O(steps / chunk + chunk) instead of O(steps)).
        step_fn: replacement for ``step``, called as ``step_fn(world, state, index=i)`` (i: the
            step's number from 0, ``step``'s ``index``).
        broadphase: see ``wrench``.
        compile: run chunks of ``compile_chunk`` steps through ``compiled_chunk``
            (the remainder runs eagerly); not combined with checkpointing.
        engine: ``torch`` (this module, the reference), ``native`` (``dejaview.sim.native``:
            the same model in C++, differentiable in both modes; float64 on the CPU) or
            ``auto`` (native where it applies). Native rollouts keep no autograd graph,
            so ``checkpoint_every``, ``compile`` and ``broadphase`` do not apply to them.
        max_steps: step budget, steps x substeps (default ``dejaview.scene.bounds.max_steps()``).
        physics: optional (B, 3), each candidate's physics (``World.physics``): the logs of
            factors on friction, unloading and stiffness; differentiable (native: reverse mode).
    Returns:
        Trajectory with T = 1 + ceil(steps / record_every) records.
    Raises:
        SimulationError: ``steps`` over the step budget (or an engine that cannot run).
    """
    steps = world.steps if steps is None else int(steps)
    if steps < 0:
        raise ValueError("steps must be >= 0")
    if record_every < 1:
        raise ValueError("record_every must be >= 1")
    reason = bounds.budget_problem(steps, world.substeps, bounds.max_steps(max_steps), "the rollout")
    if reason:
        raise SimulationError(reason)
    record_every = min(int(record_every), max(steps, 1))
    if steps > 0 and engine != "torch":
        from dejaview.sim import native

        if native.use_native(engine, world):
            if step_fn is not None:
                raise ValueError("step_fn replaces the torch engine's step; it needs engine='torch'")
            return native.native_rollout(world, state, steps, record_every, physics=physics)
    if compile and torch.is_grad_enabled() and any(world.box_bodies) and any(
            s.path is not None and s.kind == "box" for s in world.statics):
        # measured: states exact, gradients 5e-3 off (of 7e-3) under inductor, exact under dynamo's tracing
        raise SimulationError("a compiled rollout's gradients where a box body meets a moving box link are not "
                              "right under inductor (docs/robotics.md, 'Robots that move'); run it without compile")
    if physics is not None:
        if compile:
            raise ValueError("a rollout with per-candidate physics does not compile")
        world = replace(world, physics=physics)
    fn = step if step_fn is None else step_fn
    records = [state]
    record_steps = [0]
    i = 0
    use_ckpt = checkpoint_every is not None and checkpoint_every > 0 and torch.is_grad_enabled()
    while i < steps:
        if compile and steps - i >= compile_chunk:
            n = compile_chunk
            posed = tuple(world.posed(j) for j in range(i * world.substeps, (i + n) * world.substeps)) \
                if world.moving else ()
            flat = compiled_chunk(world, n)(*state.tensors(), posed)
            chunk_states = [State(*flat[4 * j: 4 * j + 4]) for j in range(n)]
        elif use_ckpt:
            n = min(checkpoint_every, steps - i)

            def chunk(*ts, n=n, first=i):
                s = State(*ts)
                outs = []
                for j in range(first, first + n):
                    s = fn(world, s, broadphase, index=j) if step_fn is None else fn(world, s, index=j)
                    outs.append(s)
                return tuple(t for o in outs for t in o.tensors())

            flat = checkpoint(chunk, *state.tensors(), use_reentrant=False)
            chunk_states = [State(*flat[4 * j: 4 * j + 4]) for j in range(n)]
        else:
            n = 1
            chunk_states = [fn(world, state, broadphase, index=i) if step_fn is None else fn(world, state, index=i)]
        for s in chunk_states:
            i += 1
            if i % record_every == 0 or i == steps:
                records.append(s)
                record_steps.append(i)
        state = chunk_states[-1]
    return Trajectory(State.stack(records), torch.tensor(record_steps), world.dt)
