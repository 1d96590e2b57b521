"""Run a scene forward from its objects' given poses and velocities.

``simulate(scene)`` is what ``dejaview simulate`` and the server's simulate
jobs both call: build the World, take the scene's initial state, roll it out
without gradients, and hand back the trajectory ready to be written as
``trajectory.csv``.
"""

from __future__ import annotations

import numbers
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from dejaview.errors import SimulationError
from dejaview.scene import bounds
from dejaview.sim.integrate import Trajectory
from dejaview.sim.world import World


RECORD_COPIES = 4
"""Copies of the recorded states a simulation holds at its peak: the records, their stacked
trajectory, and trajectory.csv's rows as they are formatted."""
NATIVE_CHUNK = 50
"""Steps per native call between progress callbacks (rounded up to a multiple of record_every)."""


def _native_chunks(world: World, state, n: int, record_every: int, callback, should_stop) -> Trajectory:
    """A native rollout of ``n`` steps in chunks, with the hooks called between chunks."""
    from dejaview.sim.native import native_rollout
    from dejaview.sim.state import State

    chunk = record_every * max(1, -(-NATIVE_CHUNK // record_every))
    records, steps, done = [state], [0], 0
    with torch.no_grad():
        while done < n:
            if should_stop is not None and should_stop():
                raise SimulationStopped(f"stopped after {done} of {n} steps")
            k = min(chunk, n - done)
            part = native_rollout(world, state, k, record_every, check_divergence=True, first_step=done)
            records.extend(State(*(t[i] for t in part.states.tensors())) for i in range(1, len(part)))
            steps.extend(done + int(s) for s in part.steps[1:])
            state = part.final
            done += k
            if callback is not None:
                callback(done, n)
    return Trajectory(State.stack(records), torch.tensor(steps), world.dt)


class SimulationStopped(Exception):
    """``should_stop`` ended a simulation before its last step (cancellation)."""


@dataclass
class SimulationRun:
    """Outcome of ``simulate``.

    Attributes:
        world: the World simulated (another backend: what its trajectory writers read, e.g.
            ``dejaview.backends.warp.BodyFrames``).
        trajectory: recorded states (T, 1, N, ...).
        steps: number of steps simulated.
        elapsed_s: wall time of the rollout (World building excluded).
        backend: the backend that ran it.
    """

    world: World
    trajectory: Trajectory
    steps: int
    elapsed_s: float
    backend: str = "spheres"

    @property
    def names(self) -> tuple[str, ...]:
        """(N,) movable body ids."""
        return tuple(self.world.names)

    @property
    def dt(self) -> float:
        return self.trajectory.dt

    def csv(self) -> str:
        """The trajectory CSV (scene-format spec, "Outputs") as text."""
        from dejaview.sim.trajectory_csv import trajectory_csv

        return trajectory_csv(self.world, self.trajectory)

    def write(self, out_dir) -> dict[str, Path]:
        """Write ``trajectory.csv`` into ``out_dir`` (created), whole or not at all
        (``dejaview.result_set``); returns ``{"trajectory": path}``.

        Raises:
            OutputError: it could not be written (a full disk...): out_dir keeps what it held.
        """
        from dejaview.result_set import write_result_set
        from dejaview.sim.trajectory_csv import write_trajectory_csv

        return write_result_set(out_dir, lambda folder: {
            "trajectory": write_trajectory_csv(folder / "trajectory.csv", self.world, self.trajectory)})


def simulate(scene, *, steps: int | None = None, record_every: int = 1,
             dtype: torch.dtype = torch.float64, callback=None, should_stop=None,
             world: World | None = None, engine: str = "auto", max_steps: int | None = None,
             memory_limit: int | None = None) -> SimulationRun:
    """Simulate a scene forward without gradients.

    Args:
        scene: a Scene (or a path to a scene file).
        steps: number of steps (default: the scene's duration / dt).
        record_every: record every k-th step (the first and last are always recorded).
        dtype: floating type of the simulation.
        callback: called as ``callback(step, steps)`` after every step (progress bars).
        should_stop: polled before every step; True raises ``SimulationStopped``.
        world: reuse an already built World of this scene.
        engine: ``auto`` | ``native`` | ``torch`` (``dejaview.sim.native.ENGINES``; auto: the
            native C++ simulator in float64, torch otherwise). Native runs call ``callback``
            and ``should_stop`` between chunks of ``NATIVE_CHUNK`` steps.
        max_steps: step budget, steps x substeps (default ``dejaview.scene.bounds.max_steps()``).
        memory_limit: bytes the process may hold (None: ``dejaview.memory.limit()``): records that
            would need more are refused before the first step.
    Returns:
        SimulationRun, every recorded number finite.
    Raises:
        SceneError: a scene file that cannot be read (or over the step budget).
        SimulationError: ``steps`` or ``record_every`` below 1, steps over the budget, or a state
            that diverged (``dejaview.sim.divergence``: naming the object, the step and the quantity).
        ResourceError: records that would need more memory than the limit (``dejaview.memory``).
        SimulationStopped: ``should_stop`` answered True.
    """
    from dejaview.scene import Scene
    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import rollout, step

    if record_every < 1:
        raise SimulationError(f"record_every must be >= 1, got {record_every}")
    max_steps = bounds.max_steps(max_steps)
    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene, max_steps=max_steps)
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, numbers.Integral):
            raise SimulationError(f"steps must be an integer, got {steps!r}")
        if steps < 1:
            raise SimulationError(f"steps must be >= 1, got {steps}")
    world = world or World.from_scene(scene, dtype=dtype, max_steps=max_steps)
    n = world.steps if steps is None else int(steps)
    reason = bounds.budget_problem(n, world.substeps, max_steps, "the simulation")
    if reason:
        raise SimulationError(reason)
    record_every = min(int(record_every), n)  # the same records, and a number C++ can hold
    from dejaview import memory

    records = n // record_every + 2
    memory.check(f"a simulation of {n} steps recording every {record_every} ({records} records of "
                 f"{world.num_bodies} bodies)",
                 RECORD_COPIES * records * world.num_bodies * 13 * torch.finfo(world.dtype).bits // 8,
                 memory_limit)
    state = initial_state(world, scene)
    done = 0

    def step_with_hooks(world_, state_, broadphase=None, index=0):
        nonlocal done
        if should_stop is not None and should_stop():
            raise SimulationStopped(f"stopped after {done} of {n} steps")
        out = step(world_, state_, broadphase, index=index)
        done += 1
        divergence.check(world_, out, done)
        if callback is not None:
            callback(done, n)
        return out

    from dejaview.sim import divergence, native

    if native.use_native(engine, world):
        start = time.perf_counter()
        traj = _native_chunks(world, state, n, record_every, callback, should_stop)
        return SimulationRun(world=world, trajectory=traj, steps=n,
                             elapsed_s=time.perf_counter() - start)
    start = time.perf_counter()
    with torch.no_grad():
        traj = rollout(world, state, steps=n, record_every=record_every, step_fn=step_with_hooks)
    return SimulationRun(world=world, trajectory=traj, steps=n, elapsed_s=time.perf_counter() - start)
