"""The backend protocol, and the problem base every backend's problem derives from.

A *backend* (``Backend``) builds problems from scenes and runs scenes forward. A *problem*
(``Problem``) maps parameters of the source's initial state (``ParameterLayout``, shared by every
backend) to a simulated trajectory and a loss, with gradients. The base owns everything but the
rollout: the loss of a trajectory (``dejaview.losses``, written once for every backend), the
objective the optimisers minimise, gradients through torch (reverse by autograd, forward by
``torch.func``), the final pose and trajectory I/O. A backend's problem supplies ``simulate``: a
``Trajectory`` of torch tensors, differentiable with respect to ``x`` in the gradient modes it
offers.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

from dejaview.errors import InferenceError
from dejaview.losses.pose import DEFAULT_ORIENTATION_WEIGHT
from dejaview.sim.gradients import GRADIENT_MODES


class Problem:
    """Parameters x (K, P) of the source's initial state -> trajectory -> loss (K,).

    A subclass sets these attributes and supplies ``simulate``, ``frames``, ``dt``,
    ``duration_steps`` and ``simulation_settings``:

    Attributes:
        backend: the backend's name; gradient_modes: the gradient modes it offers.
        layout: ParameterLayout of the source (may be replaced, e.g. per-candidate boxes).
        source: index of the source among the movable bodies.
        targets: the scene's Targets; sightings: what each observes (``dejaview.losses.targets``).
        loss_kind: ``pose`` | ``add`` | ``position``; evaluate: ``best`` | ``final``.
        steps: rollout length of the loss (up to the target time when it is pinned).
        penalties: ((body_a, body_b, weight), ...).
        orientation_weight: metres per radian in the pose loss.
        points: (M, 3) model points (object frame) for the ADD loss, or None.
        record_every: record interval of the loss's rollouts.
        evaluations: loss evaluations so far.
    """

    backend: str = ""
    gradient_modes: tuple[str, ...] = GRADIENT_MODES
    penalties: tuple = ()
    points: torch.Tensor | None = None
    record_every: int = 1

    # ------------------------------------------------------ what a backend supplies
    @property
    def frames(self):
        """What the losses and the trajectory writers read of the bodies: ``names`` (N,), ``com``
        (N, 3), ``object_position(state)``, ``body_index(name)``, ``dtype`` (a ``World`` has them)."""
        raise NotImplementedError

    def simulate(self, x: torch.Tensor, steps: int | None = None, record_every: int | None = None,
                 checkpoint: bool = False):
        """Rollout from parameters x (K, P): a ``Trajectory`` with states (T, K, N, ...) (centres of
        mass, w x y z quaternions, world velocities). ``checkpoint``: the rollout is taken for a
        reverse-mode gradient (a backend may trade time for memory)."""
        raise NotImplementedError

    def simulation_settings(self) -> dict:
        """Simulation numbers for result.json."""
        raise NotImplementedError

    def backend_options(self):
        """``BackendOptions`` that build this problem again from its scene (in a worker process):
        the backend's name and the settings of its own that the problem was built with."""
        from dejaview.backends.options import BackendOptions

        return BackendOptions.of(self.backend)

    # ------------------------------------------------------------ shared
    @property
    def num_params(self) -> int:
        return self.layout.size

    @property
    def body_names(self) -> tuple[str, ...]:
        return tuple(self.frames.names)

    @property
    def dtype(self) -> torch.dtype:
        """dtype of the parameters and losses."""
        return self.frames.dtype

    @property
    def target(self):
        """The last observation (``InferenceSettings.target``)."""
        from dejaview.scene.model import last_target

        return last_target(self.targets)

    def loss_of_trajectory(self, traj) -> torch.Tensor:
        """(K,) loss (plus weighted penalties) of a rollout."""
        from dejaview.losses import contact_penalty
        from dejaview.losses.trajectory import sightings_loss

        loss = sightings_loss(self.frames, traj, self.source, self.sightings, kind=self.loss_kind,
                              orientation_weight=self.orientation_weight, points=self.points)
        for a, b, weight in self.penalties:
            loss = loss + weight * contact_penalty(self.frames, traj, a, b)
        return loss

    def loss(self, x: torch.Tensor, checkpoint: bool = False) -> torch.Tensor:
        """Losses (K,) of parameters x (K, P)."""
        self.evaluations += 1
        return self.loss_of_trajectory(self.simulate(x, checkpoint=checkpoint))

    def value_and_grad(self, x: torch.Tensor, mode: str = "reverse") -> tuple[torch.Tensor, torch.Tensor]:
        """Losses (K,) and their gradients (K, P) by forward or reverse mode.

        Raises:
            InferenceError: an unknown mode, or one this backend does not offer.
        """
        from dejaview.sim.gradients import forward_value_and_grad, reverse_value_and_grad

        if mode not in GRADIENT_MODES:
            raise InferenceError(f"unknown gradient mode {mode!r}; choose forward or reverse")
        if mode not in self.gradient_modes:
            offered = " and ".join(self.gradient_modes)
            raise InferenceError(f"the {self.backend} backend offers {offered}-mode gradients only, not "
                                 f"{mode} mode; use --gradient {self.gradient_modes[0]}")
        if mode == "forward":
            return forward_value_and_grad(self.loss, x)
        return reverse_value_and_grad(lambda z: self.loss(z, checkpoint=True), x)

    def objective_and_grad(self, x: torch.Tensor, mode: str = "reverse") -> tuple[torch.Tensor, torch.Tensor]:
        """What the optimisers minimise: ``0.5 * loss^2`` (K,) and its gradient (K, P).

        The losses are distances (metres), close to a cone |d| around the
        optimum; squared, they are smooth and quadratic there, which is what
        L-BFGS's curvature pairs and line search need (on the cone L-BFGS
        creeps by |g|^2 per iteration). Same minimiser; ``objective_to_loss``
        turns values back into losses for reporting.
        """
        loss, grad = self.value_and_grad(x, mode)
        return 0.5 * loss * loss, loss.unsqueeze(-1) * grad

    def final_pose(self, traj, index: int = 0) -> tuple[list[float], list[float]]:
        """Object-frame position (3) and orientation (4, w x y z) of the source at the last record."""
        final = traj.final
        pos = self.frames.object_position(final)[index, self.source]
        return pos.tolist(), final.orientation[index, self.source].tolist()

    def trajectory_csv(self, traj, index: int = 0) -> str:
        """Trajectory CSV text of candidate ``index`` (every movable object)."""
        from dejaview.sim.trajectory_csv import trajectory_csv

        return trajectory_csv(self.frames, traj, index)

    def write_trajectory(self, path, traj, index: int = 0):
        """Write the trajectory CSV of candidate ``index``; returns the path."""
        from dejaview.sim.trajectory_csv import write_trajectory_csv

        return write_trajectory_csv(path, self.frames, traj, index)


@runtime_checkable
class Backend(Protocol):
    """A physics backend: problems from scenes, and scenes run forward.

    Attributes:
        name: what ``--backend`` and result.json call it.
        gradient_modes: the gradient modes its problems offer.
        simulate_options: the options its ``simulate`` takes.
    """

    name: str
    gradient_modes: tuple[str, ...]
    simulate_options: frozenset[str]

    def available(self) -> str | None:
        """None when the backend can run here, else why not (one line: what to install)."""

    def make_problem(self, scene, **options) -> Problem:
        """The ``Problem`` of a scene's ``<inference>``; ``options`` are the backend's own.

        Raises:
            InferenceError: the scene cannot be solved, or an unknown or bad option.
        """

    def simulate(self, scene, *, steps: int | None = None, record_every: int = 1, callback=None,
                 should_stop=None, **options):
        """Run a scene forward from its objects' given poses and velocities, without gradients.

        Args:
            callback: ``callback(step, steps)`` as steps complete (progress).
            should_stop: polled between steps; True raises ``SimulationStopped``.
            options: the backend's own.
        Returns:
            ``dejaview.sim.simulate.SimulationRun`` (trajectory (T, 1, N, ...), ``write(out_dir)``).
        Raises:
            SimulationError: the scene cannot be simulated, or an unknown or bad option.
        """


def check_inference(scene):
    """The scene's ``<inference>``, after the checks every backend makes before building anything.

    Raises:
        InferenceError: no inference section, nothing free, or a fixed source (checked before
            a world is built: a fixed source may leave it with no movable body at all).
    """
    inf = scene.inference
    if inf is None:
        raise InferenceError("the scene has no <inference> section: nothing to solve")
    if not inf.optimize.any():
        raise InferenceError("<optimize> frees no part of the initial state: nothing to solve")
    if any(o.id == inf.source and o.fixed for o in scene.objects):
        raise InferenceError(f"source {inf.source!r} is fixed; the source must be movable")
    return inf


def sightings_of(scene, dt: float, duration_steps: int) -> tuple:
    """What each of the scene's targets observes (``dejaview.losses.targets.resolve``)."""
    from dejaview.losses.targets import resolve

    inf = scene.inference
    return resolve(inf.targets, inf.evaluate, dt, duration_steps)


def loss_steps(scene, dt: float, duration_steps: int) -> int:
    """Rollout length of the loss: the scene's duration, or up to the latest target where every
    target's time is pinned."""
    from dejaview.losses.targets import rollout_steps

    return rollout_steps(sightings_of(scene, dt, duration_steps), duration_steps)


def loss_record_every(scene, steps: int, dt: float | None = None) -> int:
    """Record interval of the loss's rollouts of ``steps`` steps: the largest that records every
    step a target reads (``dejaview.losses.targets.record_interval``: the end alone for one target
    seen moving at the end, the rest window's steps for one seen at rest), 1 where a target takes
    the best record or a ``<penalty>`` reads every record."""
    from dejaview.losses.targets import record_interval

    inf = scene.inference
    dt = scene.simulation.dt if dt is None else dt
    return record_interval(sightings_of(scene, dt, steps), steps, penalties=bool(inf.penalties))


def objective_to_loss(value: float) -> float:
    """Inverse of ``0.5 * loss^2`` for reporting."""
    import math

    return math.sqrt(max(2.0 * value, 0.0)) if math.isfinite(value) else value


def model_points(scene, obj, dtype=torch.float64, budget: int = 256) -> torch.Tensor:
    """Model points (M, 3) of an object in its own frame for the ADD loss."""
    import numpy as np

    from dejaview.geometry.mesh import load_mesh, primitive_mesh
    from dejaview.losses import model_points as subsample

    if obj.mesh is not None:
        mesh = load_mesh(scene.resolve(obj.mesh))
    else:
        mesh = primitive_mesh(obj.shape, size=obj.size, radius=obj.radius, height=obj.height)
    pts = subsample(np.asarray(mesh.vertices), budget=budget)
    return torch.as_tensor(np.asarray(pts), dtype=dtype)
