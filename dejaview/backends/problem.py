"""An inference problem: parameters -> rollout -> loss, with gradients.

``InferenceProblem`` ties a World, the scene's other bodies' initial states,
the source's ``ParameterLayout``, the target and the loss settings together.
``loss(x)`` maps parameters (B, P) to losses (B,) and is free of
data-dependent Python branches, so it runs under ``torch.func`` transforms
(forward mode) as well as autograd (reverse mode).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from dejaview.errors import InferenceError
from dejaview.backends.params import ParameterLayout, layout_from_scene
from dejaview.sim.gradients import forward_value_and_grad, reverse_value_and_grad
from dejaview.sim.integrate import Trajectory, rollout
from dejaview.sim.rotation import normalize_quat, quat_rotate
from dejaview.sim.state import State
from dejaview.sim.world import World

DEFAULT_ORIENTATION_WEIGHT = 0.05  # metres per radian; see dejaview.losses.pose


@dataclass
class InferenceProblem:
    """Parameters of the source's initial state -> loss of the simulated outcome.

    Attributes:
        world: the World.
        layout: ParameterLayout of the source.
        source: index of the source body in the world.
        base: State (1, N, ...) of every body as given in the scene.
        target: the scene's Target.
        loss_kind: ``pose`` | ``add`` | ``position``.
        evaluate: ``best`` | ``final``.
        steps: rollout length (up to the target time when it is pinned).
        penalties: ((body_a, body_b, weight), ...).
        orientation_weight: metres per radian in the pose loss.
        points: (M, 3) model points (object frame) for the ADD loss, or None.
        checkpoint_every: reverse-mode checkpoint chunk (None: no checkpointing).
        compile: run the rollouts of gradient evaluations through ``torch.compile``
            (``rollout(compile=True)``): faster per loss + gradient than eager torch
            after a first compile of minutes (``docs/benchmarks.md``); not combined
            with checkpointing. Rollouts without autograd (screening,
            the final re-simulation) stay on ``engine``: they are few, and each grad
            mode would need its own compile.
        engine: simulation engine of the rollouts (``dejaview.sim.native.ENGINES``):
            ``auto`` (default) runs the native C++ simulator where it applies (float64
            on the CPU), the same model with exact forward- and reverse-mode gradients,
            the fastest by far (``docs/benchmarks.md``, "Simulator"); ``torch`` runs
            ``dejaview.sim.integrate``. ``compile`` implies ``torch`` for the rollouts
            it compiles.
    """

    world: World
    layout: ParameterLayout
    source: int
    base: State
    target: object
    loss_kind: str = "pose"
    evaluate: str = "best"
    steps: int = 0
    penalties: tuple = ()
    orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT
    points: torch.Tensor | None = None
    checkpoint_every: int | None = None
    record_every: int = 1
    compile: bool = False
    engine: str = "auto"
    evaluations: int = field(default=0, init=False)

    @staticmethod
    def from_scene(scene, world: World | None = None, *, dtype=torch.float64,
                   orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
                   checkpoint_every: int | None = None, max_speed: float = 3.0,
                   max_spin: float = 10.0, engine: str = "auto") -> "InferenceProblem":
        """Build the problem of a scene's ``<inference>``.

        Raises:
            InferenceError: no inference section, nothing free, fixed/unknown source or target.
        """
        from dejaview.sim.build import initial_state

        inf = check_inference(scene)
        world = world if world is not None else World.from_scene(scene, dtype=dtype)
        try:
            src = world.body_index(inf.source)
        except Exception:
            raise InferenceError(f"source {inf.source!r} is not a movable object") from None
        for p in inf.penalties:
            for name in p.between:
                known = name in world.names or any(s.name == name for s in world.statics)
                if not known:
                    raise InferenceError(f"penalty names unknown object {name!r}")
        layout = layout_from_scene(scene, dtype=world.dtype, max_speed=max_speed, max_spin=max_spin)
        if layout.size == 0:
            raise InferenceError("no free parameter: the start area pins the position and nothing "
                                 "else is free")
        steps = world.steps
        if inf.target.time is not None:
            steps = max(1, int(round(inf.target.time / world.dt)))
        points = None
        if inf.loss == "add":
            points = model_points(scene, scene.object(inf.source), world.dtype)
        return InferenceProblem(
            world=world, layout=layout, source=src, base=initial_state(world, scene),
            target=inf.target, loss_kind=inf.loss, evaluate=inf.evaluate, steps=steps,
            penalties=tuple((p.between[0], p.between[1], p.weight) for p in inf.penalties),
            orientation_weight=orientation_weight, points=points, checkpoint_every=checkpoint_every,
            engine=engine)

    @property
    def num_params(self) -> int:
        return self.layout.size

    # ----------------------------------------------------------------- rollout
    def initial_state(self, x: torch.Tensor) -> State:
        """State (B, N, ...) with the source's initial state from parameters x (B, P)."""
        s = self.layout.decode(x)
        b = x.shape[0]
        # the source alone (World.state wants every body): object-frame origin -> centre of mass
        q = normalize_quat(s["orientation"])
        com = quat_rotate(q, self.world.com[self.source].expand_as(s["position"]))
        src = (s["position"] + com, q, s["linear_velocity"], s["angular_velocity"])
        base = self.base.index(slice(0, 1))
        out = []
        for field_name, value in zip(("position", "orientation", "linear_velocity", "angular_velocity"),
                                     (t[:, None] for t in src)):
            full = getattr(base, field_name).expand(b, *getattr(base, field_name).shape[1:])
            parts = [full[:, i:i + 1] for i in range(self.world.num_bodies)]
            parts[self.source] = value
            out.append(torch.cat(parts, 1))
        return State(*out)

    def simulate(self, x: torch.Tensor, steps: int | None = None, record_every: int | None = None,
                 checkpoint: bool = False) -> Trajectory:
        """Rollout from parameters x (B, P)."""
        compiled = self.compile and torch.is_grad_enabled()
        return rollout(self.world, self.initial_state(x), steps=self.steps if steps is None else steps,
                       record_every=record_every or self.record_every,
                       checkpoint_every=self.checkpoint_every if checkpoint and not compiled else None,
                       compile=compiled, engine="torch" if compiled else self.engine)

    def loss_of_trajectory(self, traj: Trajectory) -> torch.Tensor:
        """(B,) loss (plus weighted penalties) of a rollout."""
        from dejaview.losses import contact_penalty, trajectory_loss

        t = self.target
        time = None if t.time is None else t.time
        loss = trajectory_loss(self.world, traj, self.source, t, kind=self.loss_kind,
                               evaluate=self.evaluate, time=time,
                               orientation_weight=self.orientation_weight, points=self.points)
        for a, b, weight in self.penalties:
            loss = loss + weight * contact_penalty(self.world, traj, a, b)
        return loss

    def loss(self, x: torch.Tensor, checkpoint: bool = False) -> torch.Tensor:
        """Losses (B,) of parameters x (B, P)."""
        self.evaluations += 1
        return self.loss_of_trajectory(self.simulate(x, checkpoint=checkpoint))

    def value_and_grad(self, x: torch.Tensor, mode: str = "forward") -> tuple[torch.Tensor, torch.Tensor]:
        """Losses (B,) and their gradients (B, P) by forward or reverse mode."""
        if mode == "forward":
            return forward_value_and_grad(self.loss, x)
        if mode == "reverse":
            return reverse_value_and_grad(lambda z: self.loss(z, checkpoint=True), x)
        raise InferenceError(f"unknown gradient mode {mode!r}; choose forward or reverse")

    def objective_and_grad(self, x: torch.Tensor, mode: str = "forward") -> tuple[torch.Tensor, torch.Tensor]:
        """What the optimisers minimise: ``0.5 * loss^2`` (B,) and its gradient (B, P).

        The losses are distances (metres), close to a cone |d| around the
        optimum; squared, they are smooth and quadratic there, which is what
        L-BFGS's curvature pairs and line search need (on the cone L-BFGS
        creeps by |g|^2 per iteration). Same minimiser; ``objective_to_loss``
        turns values back into losses for reporting.
        """
        loss, grad = self.value_and_grad(x, mode)
        return 0.5 * loss * loss, loss.unsqueeze(-1) * grad


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


def objective_to_loss(value: float) -> float:
    """Inverse of ``0.5 * loss^2`` for reporting."""
    import math

    return math.sqrt(max(2.0 * value, 0.0)) if math.isfinite(value) else value


def model_points(scene, obj, dtype=torch.float64, budget: int = 256) -> torch.Tensor:
    """Model points (M, 3) of an object in its own frame for the ADD loss."""
    import numpy as np

    from dejaview.geometry.mesh import load_mesh, primitive_mesh

    if obj.mesh is not None:
        mesh = load_mesh(scene.resolve(obj.mesh))
    else:
        mesh = primitive_mesh(obj.shape, size=obj.size, radius=obj.radius, height=obj.height)
    from dejaview.losses import model_points as subsample

    pts = subsample(np.asarray(mesh.vertices), budget=budget)
    return torch.as_tensor(np.asarray(pts), dtype=dtype)
