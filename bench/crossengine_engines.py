"""The cross-engine bench's engines: DejaView, and the engines that observe its cases.

Each observing engine is a function ``(scene, times, state=None) -> {t: (positions (N, 3),
orientations (N, 4) w x y z)}`` of the scene's movable objects' origins, ``state`` replacing the
source's start with a solve's ``initial_state`` (``{"source", "initial_state"}``): MuJoCo
(``mujoco_run``, the scene exported by ``dejaview.io.mjcf.export_mjcf``) and Bullet
(``bullet_engine.bullet_run``). ``ENGINES`` names them for ``--engines``; ``warp_end`` re-simulates
an answer in Warp where it runs.
"""

from __future__ import annotations

import sys

import numpy as np

from dejaview.cli.bench import bench_module

MUJOCO_TIMESTEP = 5e-6
"""Seconds: MuJoCo's time step here, the reference's (docs/physics-fidelity.md, "MuJoCo's time
step", ``timestep_study``): within 2 mm of its run at 2 us on every fidelity row and every
inference case's true start but the box sliding off the table (1.7 cm at 1.0 s, 0.4 cm at 1.2 s),
which lands on its edge and tips on or falls back. At 50 us MuJoCo's end there was 65-78 cm from
its 2 us run, and with the pairs' friction at omega_0 it fell back at 50 and 10 us and tipped on at
the other steps (a start 1-10 mm/s faster or slower flipped it at 50 and 20 us, moved it by 1 cm
at 5 us); at the export's 0.5 ms it tipped the box over the table's edge twice as fast as a rigid
box."""


def mujoco_run(scene, times, state: dict | None = None, timestep: float | None = None, contact: str = "mapped"):
    """MuJoCo's object-frame origins and orientations of every movable object at ``times``, at
    ``timestep`` (default ``MUJOCO_TIMESTEP``), its contact ``contact`` (``export_mjcf``'s: DejaView's
    mapped, or MuJoCo's own defaults).

    Returns:
        {t: (positions (N, 3), orientations (N, 4))}.
    """
    import mujoco

    from dejaview.io.mjcf import export_mjcf

    model = mujoco.MjModel.from_xml_string(export_mjcf(scene, state, timestep=timestep or MUJOCO_TIMESTEP,
                                                       contact=contact))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    ids = [model.body(o.id).id for o in scene.movable]
    marks = {round(t / model.opt.timestep): t for t in times}
    out = {}
    for k in range(max(marks) + 1):
        if k in marks:
            out[marks[k]] = (data.xpos[ids].copy(), data.xquat[ids].copy())
        mujoco.mj_step(model, data)
    return out


def dejaview_run(scene, times):
    """DejaView's (native engine) object-frame origins and orientations at ``times``."""
    import torch

    from dejaview.sim import World, rollout
    from dejaview.sim.build import initial_state

    world = World.from_scene(scene)
    steps = round(max(times) / world.dt)
    with torch.no_grad():
        traj = rollout(world, initial_state(world, scene), steps=steps, engine="native")
    pos = world.object_position(_flat(traj.states))
    out = {}
    for t in times:
        k = round(t / world.dt)
        out[t] = (pos[k].numpy(), traj.states.orientation[k, 0].numpy())
    return out


def _flat(states):
    """States (T, 1, N, ...) as a batch (T, N, ...) for ``World.object_position``."""
    from dejaview.sim.state import State

    return State(*(t[:, 0] for t in states.tensors()))


def warp_end(scene):
    """Warp's (``dejaview.backends.warp``, its defaults) end origin of the source, or None
    where Warp cannot run here."""
    try:
        from dejaview.backends.warp import simulate_scene
    except Exception:  # the warp extra is not installed
        return None
    try:
        frames, traj = simulate_scene(scene)
    except Exception as exc:  # Warp cannot build or run its kernels here
        print(f"warp: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return None
    pos = frames.object_position(_flat(traj.states))[-1]
    return pos[frames.body_index(scene.inference.source)].numpy()


def _dejaview_end(world, scene, t: float) -> np.ndarray:
    import torch

    from dejaview.sim import rollout
    from dejaview.sim.build import initial_state

    with torch.no_grad():
        traj = rollout(world, initial_state(world, scene), steps=round(t / world.dt), engine="native")
    return world.object_position(_flat(traj.states))[-1].numpy()


def bullet_run(scene, times, state: dict | None = None, timestep: float | None = None):
    """Bullet's run (``bullet_engine.bullet_run``, its mapping in that module's docstring)."""
    return bench_module("bullet_engine").bullet_run(scene, times, state, timestep)


def mujoco_default_run(scene, times, state: dict | None = None, timestep: float | None = None):
    """MuJoCo at its default contact parameters (``export_mjcf(contact="mujoco")``: soft, critically
    damped, pyramidal cone, Euler; the scene's friction carried, its restitution not) at the scene's
    own time step: the world of a MuJoCo user who writes no contact parameters, which issue 58's
    hidden cases observe in."""
    return mujoco_run(scene, times, state, timestep or scene.simulation.dt, contact="mujoco")


ENGINES = {"mujoco": mujoco_run, "bullet": bullet_run, "mujoco-default": mujoco_default_run}
"""The observing engines by name; their names as the bench prints them: ``ENGINE_NAMES``."""
ENGINE_NAMES = {"mujoco": "MuJoCo", "bullet": "Bullet", "mujoco-default": "MJdflt"}


def check_engines(names) -> tuple:
    """``names`` (a comma-separated string or a sequence) as a tuple of ``ENGINES``' keys.

    Raises:
        ValueError: an unknown or no engine, in one line.
    """
    names = tuple(n for n in (names.replace(" ", "").split(",") if isinstance(names, str) else names) if n)
    bad = [n for n in names if n not in ENGINES]
    if not names or bad:
        raise ValueError(f"engines: expected a comma-separated list of {', '.join(ENGINES)}, got {names!r}")
    return names
