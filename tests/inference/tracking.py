"""Tracked observations for the inference tests: a scene's own start simulated and seen by position."""

from __future__ import annotations

import torch

from dejaview.sim import World
from dejaview.sim.build import initial_state
from dejaview.sim.integrate import rollout


def position_targets(scene, times) -> str:
    """``<target position time>`` lines (joined for a scene text) of the scene's first body seen at
    ``times`` (s), simulated from the scene's own start in DejaView's engine, without noise."""
    world = World.from_scene(scene)
    with torch.no_grad():
        traj = rollout(world, initial_state(world, scene))
    lines = []
    for t in times:
        p = traj.states.position[int(round(t / world.dt)), 0, 0].tolist()
        lines.append(f'<target position="{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" time="{t}"/>')
    return "\n    ".join(lines)
