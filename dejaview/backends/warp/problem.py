"""The ``warp`` backend's problem: rollouts in ``warp.sim``, everything else in ``Problem``.

Warp's recorded states reach torch through ``wp.to_torch`` inside an autograd Function
(``_WarpRollout``) whose backward runs the ``wp.Tape``: the losses are ``dejaview.losses``, as on
every backend, and the gradient chains through the layout's decode in torch. Reverse mode only
(``gradient="forward"`` is an error). ``<penalty>`` terms are not supported. The parameters, the
decode and the losses are float64 in torch; ``warp.sim`` itself computes in float32.

K candidates run in chunks of at most ``max_envs`` environments of one Warp model (default 8; a
reverse pass keeps every step's contacts, so memory grows with chunk x steps).
"""

from __future__ import annotations

import torch

from dejaview.backends.base import Problem, check_inference, loss_steps, model_points, sightings_of
from dejaview.errors import InferenceError


class _WarpRollout(torch.autograd.Function):
    """Initial body_q (E, N, 7), body_qd (E, N, 6) -> recorded body_q (T, E, N, 7), body_qd
    (T, E, N, 6), all float64; the backward runs Warp's tape."""

    @staticmethod
    def forward(ctx, body_q, body_qd, sim, steps, record_every, slot):
        grad = ctx.needs_input_grad[0] or ctx.needs_input_grad[1]
        run = sim.run(body_q.detach().cpu().numpy(), body_qd.detach().cpu().numpy(), steps,
                      record_every=record_every, grad=grad, slot=slot)
        ctx.run = run
        kept = torch.tensor(run.kept)
        ctx.mark_non_differentiable(kept)
        return run.body_q, run.body_qd, kept

    @staticmethod
    def backward(ctx, g_q, g_qd, _):
        gq, gqd = ctx.run.backward(g_q, g_qd)
        ctx.run = None
        return gq, gqd, None, None, None, None


class WarpProblem(Problem):
    """A scene's inference problem on Warp (``dejaview.backends.base.Problem``).

    Attributes:
        sim: the ``WarpSimulator``.
        max_envs: most candidates simulated as one Warp model.
        The others: as ``Problem``.
    """

    backend = "warp"
    gradient_modes = ("reverse",)

    def __init__(self, sim, layout, source: int, targets, sightings, loss_kind: str, evaluate: str,
                 steps: int, orientation_weight: float, points, max_envs: int):
        self.sim = sim
        self.layout = layout
        self.source = source
        self.targets = tuple(targets)
        self.sightings = tuple(sightings)
        self.loss_kind = loss_kind
        self.evaluate = evaluate
        self.steps = steps
        self.orientation_weight = orientation_weight
        self.points = points
        self.max_envs = max_envs
        self.record_every = 1
        self.evaluations = 0

    @classmethod
    def from_scene(cls, scene, *, integrator: str | None = None, substeps: int | None = None,
                   iterations: int | None = None, restitution: bool | None = None,
                   device: str | None = None, max_envs: int = 8,
                   orientation_weight: float | None = None, max_speed: float = 3.0,
                   max_spin: float = 10.0) -> "WarpProblem":
        """Build the problem of a scene's ``<inference>``.

        Args:
            scene: a Scene.
            integrator, substeps, iterations, restitution: override the ``warp-*`` attributes
                (``dejaview.backends.warp.settings``).
            device: Warp device (default ``cuda`` if present, else ``cpu``).
            max_envs: most candidates per Warp model.
            orientation_weight: metres per radian (default as ``dejaview.losses``).
        Raises:
            InferenceError: as ``SpheresProblem.from_scene``, plus ``<penalty>`` terms.
        """
        from dejaview.backends.params import layout_from_scene
        from dejaview.backends.warp.model import WarpSimulator
        from dejaview.losses.pose import DEFAULT_ORIENTATION_WEIGHT

        inf = check_inference(scene)
        if inf.penalties:
            raise InferenceError("the warp backend does not support <penalty> terms; use --backend spheres")
        if isinstance(max_envs, bool) or not isinstance(max_envs, int) or max_envs < 1:
            raise InferenceError(f"max_envs must be a positive integer, got {max_envs!r}")
        sim = WarpSimulator.from_scene(scene, device=device, integrator=integrator, substeps=substeps,
                                       iterations=iterations, restitution=restitution)
        if inf.source not in sim.names:
            raise InferenceError(f"source {inf.source!r} is not a movable object")
        layout = layout_from_scene(scene, dtype=torch.float64, max_speed=max_speed, max_spin=max_spin)
        if layout.size == 0:
            raise InferenceError("no free parameter: the start area pins the position and nothing else is free")
        points = model_points(scene, scene.object(inf.source)) if inf.loss == "add" else None
        return cls(sim, layout, sim.names.index(inf.source), inf.targets,
                   sightings_of(scene, sim.dt, sim.duration_steps), inf.loss, inf.evaluate,
                   loss_steps(scene, sim.dt, sim.duration_steps),
                   DEFAULT_ORIENTATION_WEIGHT if orientation_weight is None else orientation_weight,
                   points, max_envs)

    # ------------------------------------------------------------ backend surface
    @property
    def frames(self):
        return self.sim.frames

    @property
    def dt(self) -> float:
        return self.sim.dt

    @property
    def duration_steps(self) -> int:
        return self.sim.duration_steps

    def __repr__(self) -> str:
        s = self.sim.settings
        return (f"WarpProblem({self.sim.names}, source={self.source}, P={self.num_params}, "
                f"{s['integrator']}, {s['substeps']} substep(s), device={self.sim.device})")

    def simulation_settings(self) -> dict:
        """Simulation numbers for result.json."""
        return {"dt": self.sim.dt, "steps": self.steps, "device": self.sim.device, **self.sim.settings}

    # -------------------------------------------------------------- rollout
    def initial_bodies(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Warp's body_q (K, N, 7: origin, x y z w) and body_qd (K, N, 6: angular, linear) with the
        source's initial state from parameters x (K, P); differentiable with respect to x."""
        s = self.layout.decode(x)
        q = s["orientation"] / s["orientation"].norm(dim=-1, keepdim=True)
        k = x.shape[0]
        base_q, base_qd = (torch.as_tensor(a, dtype=x.dtype) for a in self.sim.base_state(k))
        src_q = torch.cat([s["position"], q[:, [1, 2, 3, 0]]], -1)[:, None]
        src_qd = torch.cat([s["angular_velocity"], s["linear_velocity"]], -1)[:, None]
        i = self.source
        body_q = torch.cat([base_q[:, :i], src_q, base_q[:, i + 1:]], 1)
        body_qd = torch.cat([base_qd[:, :i], src_qd, base_qd[:, i + 1:]], 1)
        return body_q, body_qd

    def simulate(self, x: torch.Tensor, steps: int | None = None, record_every: int | None = None,
                 checkpoint: bool = False):
        """Rollout from parameters x (K, P): a ``Trajectory`` with states (T, K, N, ...),
        differentiable with respect to x in reverse mode."""
        steps = self.steps if steps is None else int(steps)
        body_q, body_qd = self.initial_bodies(x.to(torch.float64))
        parts = []
        for slot, start in enumerate(range(0, x.shape[0], self.max_envs)):
            sl = slice(start, start + self.max_envs)
            parts.append(_WarpRollout.apply(body_q[sl], body_qd[sl], self.sim, steps,
                                            record_every or self.record_every, slot))
        kept = parts[0][2].tolist()
        return self.sim.trajectory(kept, torch.cat([p[0] for p in parts], 1), torch.cat([p[1] for p in parts], 1))
