"""The ``spheres`` backend: DejaView's sphere-packing simulator behind the backend interface.

``SpheresProblem`` wraps an ``InferenceProblem`` and adds what the interface
asks beyond it (final pose, trajectory CSV, settings). It holds no state of
its own: every other attribute is read from and written to the wrapped
problem, so ``problem.compile = True``, a replaced ``layout`` or the
``evaluations`` counter act on the one ``InferenceProblem`` (``.inner``).
"""

from __future__ import annotations

import torch

from dejaview.backends.problem import InferenceProblem


class SpheresProblem:
    """An ``InferenceProblem`` with the backend interface (see ``dejaview.backends``)."""

    __slots__ = ("inner",)
    backend = "spheres"
    gradient_modes = ("forward", "reverse")

    def __init__(self, inner: InferenceProblem):
        object.__setattr__(self, "inner", inner)

    @classmethod
    def from_scene(cls, scene, **options) -> "SpheresProblem":
        """``InferenceProblem.from_scene(scene, **options)``, wrapped."""
        return cls(InferenceProblem.from_scene(scene, **options))

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __setattr__(self, name, value):
        setattr(self.inner, name, value)

    def __repr__(self) -> str:
        return f"SpheresProblem({self.inner.world.names}, source={self.inner.source}, P={self.inner.num_params})"

    # ------------------------------------------------------------ interface
    @property
    def dtype(self) -> torch.dtype:
        return self.inner.world.dtype

    @property
    def dt(self) -> float:
        return self.inner.world.dt

    @property
    def body_names(self) -> tuple[str, ...]:
        return tuple(self.inner.world.names)

    @property
    def duration_steps(self) -> int:
        return self.inner.world.steps

    def final_pose(self, traj, index: int = 0) -> tuple[list[float], list[float]]:
        """Object-frame position (3) and orientation (4, w x y z) of the source at the last record."""
        final = traj.final
        world = self.inner.world
        pos = world.object_position(final)[index, self.inner.source]
        return pos.tolist(), final.orientation[index, self.inner.source].tolist()

    def trajectory_csv(self, traj, index: int = 0) -> str:
        """Trajectory CSV text of candidate ``index`` (every movable object)."""
        from dejaview.io.trajectory import trajectory_csv

        return trajectory_csv(self.inner.world, traj, index)

    def write_trajectory(self, path, traj, index: int = 0):
        """Write the trajectory CSV of candidate ``index``; returns the path."""
        from dejaview.io.trajectory import write_trajectory_csv

        return write_trajectory_csv(path, self.inner.world, traj, index)

    def simulation_settings(self) -> dict:
        """Simulation numbers for result.json."""
        w = self.inner.world
        return {"dt": w.dt, "substeps": w.substeps, "steps": self.inner.steps}
