"""The posterior over the source's start: likelihood of the observed end times the prior.

The objective of the default search (``dejaview.inference.search``) is the
negative log posterior of the free parameters x (``ParameterLayout``), written
as a nonlinear least-squares problem::

    -log p(x | end) = 0.5 * |R(x)|^2 + const,     R = [misfit / noise ; prior residuals]

Residuals (physical units divided by standard deviations, so each is
dimensionless and the sum of squares is a chi-square):

- observation (``<observation sigma angle-sigma>``): the source's COM position
  minus the target's (3, metres / ``sigma``) and the rotation vector from the
  target orientation to the simulated one (3, radians / ``angle_sigma``); the
  ``position`` loss compares object-frame origins (3); the ``add`` loss is one
  residual, the ADD distance / ``sigma``. With ``evaluate="best"`` the record
  whose chi-square is smallest is compared (its choice is not differentiated),
  ``final`` the last, a ``time`` on the target the nearest record. Target
  velocities, where given, add ``velocity_weight * (v - v*) / sigma``
  (``dejaview.losses.trajectory``), and each ``<penalty>`` its weighted
  distance / ``sigma``.
- prior (``<prior speed spin tilt>``): each free velocity component over
  ``speed`` / ``spin`` (zero-mean normal), the orientation's rotation vector
  away from the ``<pose>`` orientation over ``tilt``. The start position is
  uniform in the start area (the layout keeps it inside). An attribute left out
  is a flat prior within the bounds ``speed_bound`` / ``spin_bound``: a
  residual ``(|v| - bound) / (bound_softness * bound)`` beyond them, zero
  inside, so the search stays in a plausible range without preferring any
  value in it. Orientation without ``tilt`` is flat on SO(3).

Feasibility: a start in which the source interpenetrates another object is not
a past. ``Posterior.cost`` gives such candidates an infinite cost without
simulating them, using ``feasible`` (``dejaview.geometry.collision`` with
python-fcl on the exact meshes, where available).

Model uncertainty (``<model-uncertainty>``, ``dejaview.inference.model_uncertainty``): the
observation and penalty residuals of K physics variants, each over ``sqrt(K)``, replace the one
simulator's: the mean over the variants of the log-likelihood.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dejaview.errors import InferenceError
from dejaview.sim.rotation import (geodesic_angle, normalize_quat, quat_conjugate, quat_multiply, quat_rotate,
                                   quat_to_rotvec)
from dejaview.sim.state import STATE_WIDTH, State

@dataclass(frozen=True)
class PosteriorSettings:
    """The resolved ``<prior>`` and ``<observation>`` (None: flat prior within the bounds).

    The defaults are the implementation's (the spec leaves them to it; each is written into
    ``result.json``).

    Attributes:
        sigma: observation noise of a position (m; default 5 mm, a robot's pose estimate).
        angle_sigma: of an orientation (rad; default 0.05, 2.9 degrees).
        rest_speed: noise with which "at rest" observes the source's mean speed (m/s;
            ``dejaview.losses.targets``; default 0.02: a tracker sees 2 mm of drift in 0.1 s).
        rest_spin: ... its mean spin (rad/s; default 0.2: a mug settled on its side still rocks by
            about 0.02 rad in 0.1 s, measured on mug_off_counter's truth).
        speed, spin, tilt: prior standard deviations (m/s, rad/s, rad), or None: flat.
        speed_bound: bound of the flat prior on the start's linear speed (m/s; default 5).
        spin_bound: of its spin (rad/s; default 50: a 5 cm ball rolling at 2.5 m/s).
        bound_softness: beyond a flat prior's bound the residual grows by 1 per this fraction of it.
        feasibility_margin: a start whose source overlaps another object by more than this (m) is
            infeasible (resting contact overlaps by the contact model's fraction of a millimetre).
    """

    sigma: float = 0.005
    angle_sigma: float = 0.05
    rest_speed: float = 0.02
    rest_spin: float = 0.2
    speed: float | None = None
    spin: float | None = None
    tilt: float | None = None
    speed_bound: float = 5.0
    spin_bound: float = 50.0
    bound_softness: float = 0.05
    feasibility_margin: float = 0.003

    @staticmethod
    def from_scene(scene) -> "PosteriorSettings":
        """The scene's ``<prior>`` and ``<observation>`` with the defaults filled in.

        A ``<heatmap sigma>`` given without ``<observation>`` is read as ``<observation sigma>``
        (scene-format spec, "Additions to version 1").
        """
        inf = scene.inference
        prior, obs = inf.prior, inf.observation
        sigma = PosteriorSettings.sigma
        if obs is not None and obs.sigma is not None:
            sigma = obs.sigma
        elif obs is None and inf.heatmap is not None:
            sigma = inf.heatmap.sigma
        out = PosteriorSettings(
            sigma=float(sigma),
            angle_sigma=float(obs.angle_sigma) if obs is not None and obs.angle_sigma is not None
            else PosteriorSettings.angle_sigma,
            rest_speed=float(obs.rest_speed) if obs is not None and obs.rest_speed is not None
            else PosteriorSettings.rest_speed,
            rest_spin=float(obs.rest_spin) if obs is not None and obs.rest_spin is not None
            else PosteriorSettings.rest_spin,
            speed=None if prior is None or prior.speed is None else float(prior.speed),
            spin=None if prior is None or prior.spin is None else float(prior.spin),
            tilt=None if prior is None or prior.tilt is None else float(prior.tilt))
        out.check()
        return out

    def check(self) -> None:
        """One-line InferenceError for a non-positive or non-finite value."""
        for name in ("sigma", "angle_sigma", "rest_speed", "rest_spin", "speed", "spin", "tilt", "speed_bound",
                     "spin_bound"):
            v = getattr(self, name)
            if v is None and name in ("speed", "spin", "tilt"):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise InferenceError(f"{name.replace('_', '-')} must be a positive number, got {v!r}")

    def to_json(self) -> dict:
        """``result.json``'s ``prior`` and ``observation``: every value in force, flat ones as null
        beside their bounds."""
        return {"observation": {"sigma": self.sigma, "angle_sigma": self.angle_sigma,
                                "rest_speed": self.rest_speed, "rest_spin": self.rest_spin},
                "prior": {"speed": self.speed, "spin": self.spin, "tilt": self.tilt,
                          "position": "uniform in the start area",
                          "speed_bound": None if self.speed is not None else self.speed_bound,
                          "spin_bound": None if self.spin is not None else self.spin_bound}}


class Posterior:
    """Negative log posterior of an ``SpheresProblem``'s parameters, as least-squares residuals.

    Args:
        problem: the spheres backend's ``SpheresProblem`` (rollouts, layout, target, penalties).
        settings: ``PosteriorSettings``.
        feasible: optional ``(position (B, 3), orientation (B, 4)) -> (B,) bool``: is the source's
            start, object-frame origin and orientation, free of interpenetration?
        model: optional ``ModelVariants`` (``dejaview.inference.model_uncertainty``): the
            likelihood averages over these physics variants.
    """

    def __init__(self, problem, settings: PosteriorSettings, feasible=None, model=None):
        self.problem = problem
        self.settings = settings
        self.feasible_fn = feasible
        self.model = model
        self.rollouts = 0
        """Candidate rollouts simulated so far (a batch of B counts B)."""
        self.jacobians = 0
        """Candidate residual Jacobians computed so far."""
        world = problem.world
        dt = world.dtype
        com = world.com[problem.source]
        self.sightings = tuple(problem.sightings)
        """The scene's targets as compared (``dejaview.losses.targets.Sighting``), in file order."""
        self._goals = []  # per sighting: target origin (3,), orientation (4,) or None, its COM (3,)
        for sighting in self.sightings:
            t = sighting.target
            origin = torch.as_tensor(t.position, dtype=dt)
            q = None if t.orientation is None else normalize_quat(torch.as_tensor(t.orientation, dtype=dt))
            self._goals.append((origin, q, None if q is None else origin + quat_rotate(q, com)))
        anchor = self.sightings.index(_anchor(self.sightings))
        # the last observation (the end's), which dejaview.inference.symmetry aligns rollouts to
        self._target_origin, self._target_q, self._target_com = self._goals[anchor]
        if self._target_q is None:
            self._target_com = None

    @classmethod
    def from_scene(cls, scene, *, problem=None, backend=None, world=None, collision=None) -> "Posterior":
        """The posterior of a scene's source: its observations (``<target>``s and ``<observation>``
        noise), ``<prior>``, the start area's feasibility and ``<model-uncertainty>``'s variants.

        Args:
            scene: a Scene with an ``<inference>`` section.
            problem: the spheres backend's problem, if built already (else built from ``backend``,
                a name or ``BackendOptions`` of the spheres backend, and ``world``).
            collision: the scene's ``SceneCollision``, if built already (``start_area``).
        Raises:
            InferenceError: a backend without residual Jacobians (the posterior needs the spheres
                backend's), or a scene the inference cannot take (``check_inference``).
        """
        from dejaview.backends import BackendOptions, as_problem
        from dejaview.backends.base import check_inference
        from dejaview.inference.model_uncertainty import ModelVariants

        check_inference(scene)
        if problem is None:
            options = BackendOptions.of(backend)
            problem = options.make_problem(scene, **({} if world is None else {"world": world}))
        problem = as_problem(problem)
        if problem.backend != "spheres":
            raise InferenceError(f"the posterior needs the spheres backend's residual Jacobians, not the "
                                 f"{problem.backend} backend's")
        settings = PosteriorSettings.from_scene(scene)
        feasible = feasibility_check(scene, problem, margin=settings.feasibility_margin, collision=collision)
        return cls(problem, settings, feasible=feasible,
                   model=ModelVariants.from_scene(scene, problem.world))

    def with_model(self, model) -> "Posterior":
        """The same posterior averaged over other physics variants (``ModelVariants``; None: the
        scene's own physics alone), counting its own rollouts."""
        return Posterior(self.problem, self.settings, feasible=self.feasible_fn, model=model)

    def without_model(self) -> "Posterior":
        """``with_model(None)``."""
        return self.with_model(None)

    def restricted(self, sightings: tuple) -> "Posterior":
        """The posterior of the observations ``sightings`` alone (a tracked source's first moments,
        all timed): rollouts stop at the last of them. On the scene's own physics."""
        from dataclasses import replace

        from dejaview.losses.targets import record_interval

        steps = max(sg.step for sg in sightings)
        problem = replace(self.problem, sightings=tuple(sightings), steps=steps,
                          record_every=record_interval(sightings, steps, penalties=bool(self.problem.penalties)))
        return Posterior(problem, self.settings, feasible=self.feasible_fn)

    # ---------------------------------------------------------------- residuals
    @property
    def layout(self):
        return self.problem.layout

    @property
    def prior_is_flat(self) -> bool:
        """No ``<prior>`` deviation applies to a free block (bounds aside, every start is as
        likely as any other)."""
        s, free = self.settings, self.layout.free
        return not ((free["orientation"] and s.tilt is not None)
                    or (free["linear_velocity"] and s.speed is not None)
                    or (free["angular_velocity"] and s.spin is not None))

    def _kind(self, sighting) -> str:
        """The loss a sighting is compared by: the scene's, ``position`` where its target observed
        the position alone."""
        return self.problem.loss_kind if sighting.orientation_observed else "position"

    def columns(self, sighting) -> int:
        """Observation residuals of one sighting: 6 for a pose, 3 for a position, 1 for ADD, plus 3
        per target velocity, plus 6 per part of the window where lying still is observed."""
        from dejaview.losses.targets import REST_PARTS

        t = sighting.target
        n = {"pose": 6, "position": 3, "add": 1}[self._kind(sighting)]
        n += 3 * (t.linear_velocity is not None) + 3 * (t.angular_velocity is not None)
        return n + (6 * REST_PARTS if sighting.at_rest else 0)

    @property
    def num_observed(self) -> int:
        """Observation residuals per candidate (``columns`` summed over the sightings)."""
        return sum(self.columns(s) for s in self.sightings)

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """Draws (n, P) from the prior: position uniform in the start area, orientation and
        velocities normal where the prior gives a standard deviation, else the layout's
        uniform draws (``ParameterLayout.sample``: any orientation, velocities in a ball)."""
        lay, s = self.layout, self.settings
        x = lay.sample(n, generator).to(torch.float64)
        for block, sd in (("orientation", s.tilt), ("linear_velocity", s.speed),
                          ("angular_velocity", s.spin)):
            cols = lay.block_slice(block)
            if sd is not None and cols.stop > cols.start:
                x[:, cols] = sd / lay.scale[block] * torch.randn(n, cols.stop - cols.start,
                                                                  generator=generator, dtype=x.dtype)
        return x

    def observation_residuals(self, traj) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals of every observation, and the scene's loss.

        Args:
            traj: Trajectory of the candidates, states (T, B, N, ...), recording the steps the
                sightings read (or every step).
        Returns:
            residuals (B, M_obs), the sightings' in file order (``columns`` each), and the scene's
            per-record loss (B,) in metres at the compared records (the sightings' in quadrature;
            ``SpheresProblem.loss_of_trajectory`` without penalties and rest).
        """
        parts, losses = [], []
        for sighting, goal in zip(self.sightings, self._goals):
            r, loss = self._sighting_residuals(traj, sighting, goal)
            parts.append(r)
            losses.append(loss)
        loss = losses[0] if len(losses) == 1 else torch.sqrt(sum(v * v for v in losses))
        return torch.cat(parts, -1), loss

    def _sighting_residuals(self, traj, sighting, goal) -> tuple[torch.Tensor, torch.Tensor]:
        """One sighting's residuals (B, columns) and the scene's loss (B,) at its record."""
        from dejaview.losses import LOSSES
        from dejaview.losses.targets import REST_PARTS, record_index, rest_velocities

        p, s = self.problem, self.settings
        body, world, st = p.source, p.world, traj.states
        origin, q_goal, com_goal = goal
        kind = self._kind(sighting)
        b = torch.arange(st.position.shape[1])
        if sighting.step is None:  # the record that fits best, per candidate (its choice not differentiated)
            k = self._best_records(st, sighting, goal)
        else:
            k = torch.full_like(b, record_index(traj.steps, sighting.step))
        at = State(*(t[k, b] for t in st.tensors()))  # (B, N, ...)
        pos, q = at.position[:, body], at.orientation[:, body]
        if kind == "position":
            origin_sim = pos - quat_rotate(q, world.com[body].expand_as(pos))
            parts = [(origin_sim - origin) / s.sigma]
        elif kind == "add":
            one = State(*(t.unsqueeze(0) for t in at.tensors()))
            parts = [LOSSES["add"](world, body, one, origin, q_goal, points=p.points)[0].unsqueeze(-1) / s.sigma]
        else:
            rel = quat_multiply(q, quat_conjugate(q_goal).expand_as(q))
            parts = [(pos - com_goal) / s.sigma, quat_to_rotvec(rel) / s.angle_sigma]
        parts += self._velocity_residuals(at, sighting.target)
        if sighting.at_rest:
            lin, ang = rest_velocities(traj, body, sighting)  # (B, parts, 3)
            scale = 1.0 / math.sqrt(REST_PARTS)
            parts += [lin.flatten(1) * (scale / s.rest_speed), ang.flatten(1) * (scale / s.rest_spin)]
        with torch.no_grad():
            one = State(*(t.detach().unsqueeze(0) for t in at.tensors()))
            loss = LOSSES[kind](world, body, one, origin, q_goal if q_goal is not None else _IDENTITY_Q,
                                orientation_weight=p.orientation_weight, points=p.points)[0]
        return torch.cat(parts, -1), loss

    def _velocity_residuals(self, at, target) -> list[torch.Tensor]:
        """Residuals (..., 3) of the source's velocities at states ``at`` (..., N, ...) against the
        target's, where it gives them (linear, then angular)."""
        from dejaview.losses.trajectory import DEFAULT_VELOCITY_WEIGHT

        p, s = self.problem, self.settings
        out = []
        for value, field, sd in ((target.linear_velocity, "linear_velocity", s.sigma),
                                 (target.angular_velocity, "angular_velocity", s.angle_sigma)):
            if value is not None:
                v = torch.as_tensor(value, dtype=p.world.dtype)
                out.append(DEFAULT_VELOCITY_WEIGHT * (getattr(at, field)[..., p.source, :] - v) / sd)
        return out

    def _best_records(self, st, sighting, goal) -> torch.Tensor:
        """(B,) index of the record (of states (T, B, N, ...)) whose residuals' chi-square is least,
        per candidate: the pose's squared and summed (the orientation's by its geodesic angle, the
        length of its rotation vector, without computing those), the ADD's by the centres of mass,
        plus the velocities'."""
        p, s = self.problem, self.settings
        origin, q_goal, com_goal = goal
        with torch.no_grad():
            pos, q = st.position[..., p.source, :], st.orientation[..., p.source, :]
            if self._kind(sighting) == "position":
                pos = pos - quat_rotate(q, p.world.com[p.source].expand_as(pos))
                chi2 = (((pos - origin) / s.sigma) ** 2).sum(-1)
            else:
                chi2 = (((pos - com_goal) / s.sigma) ** 2).sum(-1)
                chi2 = chi2 + (geodesic_angle(q_goal.expand_as(q), q) / s.angle_sigma) ** 2
            for part in self._velocity_residuals(st, sighting.target):
                chi2 = chi2 + (part ** 2).sum(-1)
            return chi2.argmin(0)

    def prior_residuals(self, x: torch.Tensor) -> torch.Tensor:
        """Prior residuals (B, M_prior) of parameters x (B, P) (module docstring)."""
        s, lay = self.settings, self.layout
        dec = lay.decode(x)
        parts = []
        if lay.free["orientation"] and s.tilt is not None:
            i = lay.block_slice("orientation")
            parts.append(lay.scale["orientation"] * x[:, i] / s.tilt)
        for block, sd, bound in (("linear_velocity", s.speed, s.speed_bound),
                                 ("angular_velocity", s.spin, s.spin_bound)):
            if not lay.free[block]:
                continue
            v = dec[block]
            if sd is not None:
                parts.append(v / sd)
            else:
                norm = torch.sqrt((v * v).sum(-1, keepdim=True) + 1e-24)
                parts.append(torch.relu(norm - bound) / (self.settings.bound_softness * bound))
        cols = lay.block_slice("physics")
        if cols.stop > cols.start:  # standard normals (dejaview.sim.physics)
            parts.append(x[:, cols])
        if not parts:
            return x[:, :0]
        return torch.cat(parts, -1)

    @property
    def variants(self) -> int:
        """Physics variants the likelihood averages over (1 without model uncertainty)."""
        return 1 if self.model is None else self.model.count

    def trajectories(self, x: torch.Tensor, checkpoint: bool = False) -> list:
        """The rollouts of parameters x (B, P) the likelihood compares: one per physics variant
        (``variants``), each a Trajectory (T, B, N, ...)."""
        p = self.problem
        if self.model is None:
            return [p.simulate(x, checkpoint=checkpoint)]
        return self.model.trajectories(p, x, checkpoint=checkpoint)

    def residuals(self, x: torch.Tensor, traj=None, checkpoint: bool = False
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """All residuals R (B, M) of parameters x (B, P), and the scene's loss (B,) in metres.

        Columns: the ``num_observed`` observation residuals of each of the ``variants`` physics
        variants first (each over sqrt(variants)), then the penalties' and the prior's. A given
        ``traj`` is the one simulator's (no variants), or a list of them (``trajectories``: one
        per variant, as ``dejaview.inference.symmetry`` moves them); the loss is the variants'
        mean."""
        if traj is None:
            trajs = self.trajectories(x, checkpoint=checkpoint)
        else:
            trajs = list(traj) if isinstance(traj, (list, tuple)) else [traj]
        p = self.problem
        scale = 1.0 / math.sqrt(len(trajs))
        obs, pens, losses = [], [], []
        for t in trajs:
            o, loss = self.observation_residuals(t)
            obs.append(o * scale)
            losses.append(loss)
            if p.penalties:
                from dejaview.losses import contact_penalty

                pen = sum(w * contact_penalty(p.world, t, a, b) for a, b, w in p.penalties)
                pens.append(pen.unsqueeze(-1) * (scale / self.settings.sigma))
        parts = obs + pens + [self.prior_residuals(x)]
        return torch.cat(parts, -1), torch.stack(losses).mean(0)

    # ---------------------------------------------------------------- evaluation
    def feasible(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) bool: the starts of parameters x (B, P) are free of interpenetration."""
        if self.feasible_fn is None:
            return torch.ones(x.shape[0], dtype=torch.bool)
        with torch.no_grad():
            dec = self.layout.decode(x)
        return torch.as_tensor(self.feasible_fn(dec["position"], dec["orientation"]), dtype=torch.bool)

    def cost(self, x: torch.Tensor, feasibility: bool = True, trajs: list | None = None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Negative log posterior (B,), observation chi-square (B,) and the scene's loss (B,) of
        parameters x (B, P), without gradients. Infeasible starts and non-finite results cost inf
        (infeasible ones are not simulated). ``feasibility=False``: every start is simulated as
        if feasible (for a caller that checks only the starts it keeps). ``trajs``: the rollouts
        of x already known (``trajectories``), so none is simulated."""
        b = x.shape[0]
        inf = torch.full((b,), math.inf, dtype=x.dtype)
        cost, chi2, loss = inf.clone(), inf.clone(), inf.clone()
        ok = self.feasible(x) if feasibility else torch.ones(b, dtype=torch.bool)
        if not bool(ok.any()):
            return cost, chi2, loss
        xs = x[ok]
        with torch.no_grad():
            if trajs is None:
                r, l_ = self.residuals(xs)
                self.rollouts += xs.shape[0]
            else:
                r, l_ = self.residuals(xs, traj=[t.select(ok) for t in trajs])
        c = 0.5 * (r * r).sum(-1)
        finite = torch.isfinite(c)
        obs = r[:, :self.num_observed * self.variants]  # ``residuals`` puts the observation's first
        cost[ok] = torch.where(finite, c, torch.full_like(c, math.inf))
        chi2[ok] = torch.where(finite, (obs * obs).sum(-1), torch.full_like(c, math.inf))
        loss[ok] = torch.where(finite, l_, torch.full_like(c, math.inf))
        return cost, chi2, loss

    def jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals R (B, M) and their exact Jacobian dR/dx (B, M, P).

        One rollout per physics variant with gradients and one reverse pass per residual. The
        native engine's passes run its adjoint back through each rollout, or, where the rows that
        reach a rollout (``variants`` x ``num_observed``) are at least as many as the 13N columns
        of its state Jacobians, are products with the Jacobians it carried (``phi``: under model
        uncertainty with one moving body; docs/benchmarks.md has the measured cost).
        """
        from dejaview.sim import native

        bodies = self.problem.world.num_bodies
        path = "phi" if STATE_WIDTH * bodies <= self.variants * self.num_observed else "adjoint"
        x = x.detach().clone().requires_grad_(True)
        with torch.enable_grad(), native.preferring(path):
            r, _ = self.residuals(x, checkpoint=True)
            rows = []
            m = r.shape[1]
            for i in range(m):
                g, = torch.autograd.grad(r[:, i].sum(), x, retain_graph=i < m - 1, allow_unused=True)
                rows.append(torch.zeros_like(x) if g is None else g)
        self.jacobians += x.shape[0]
        return r.detach(), torch.stack(rows, 1)


_IDENTITY_Q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
"""Stands for the unobserved orientation of a position-only target in a ``position`` loss (unread)."""


def _anchor(sightings):
    """The sighting of the last observation (``InferenceSettings.target``): the one without a
    time, else the latest."""
    untimed = [s for s in sightings if s.time is None]
    return untimed[0] if untimed else max(sightings, key=lambda s: s.time)


def feasibility_check(scene, problem, margin: float = PosteriorSettings.feasibility_margin, collision=None):
    """``(position (B, 3), orientation (B, 4)) -> (B,) bool`` for ``Posterior``: the source, placed
    at each start, overlaps no other object (at its scene pose) by more than ``margin`` metres,
    decided on the exact geometry by python-fcl (``dejaview.geometry.collision``; ``collision``: the
    scene's ``SceneCollision`` to reuse, else built here)."""
    from dejaview.geometry.collision import SceneCollision

    collision = SceneCollision(scene) if collision is None else collision
    source = scene.inference.source

    def feasible(position: torch.Tensor, orientation: torch.Tensor):
        hit, _, _ = collision.penetration(source, position.detach().cpu().numpy(),
                                          orientation.detach().cpu().numpy(), margin=margin,
                                          decide_only=True)
        return ~torch.as_tensor(hit, dtype=torch.bool)

    return feasible
