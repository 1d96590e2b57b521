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
  is a flat prior within the bounds ``SPEED_BOUND`` / ``SPIN_BOUND``: a
  residual ``(|v| - bound) / (BOUND_SOFTNESS * bound)`` beyond them, zero
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
from dejaview.sim.state import State

DEFAULT_SIGMA = 0.005
"""Metres: default standard deviation of the observed end position (a robot's pose estimate)."""
DEFAULT_ANGLE_SIGMA = 0.05
"""Radians (2.9 degrees): default standard deviation of the observed end orientation."""
SPEED_BOUND = 5.0
"""m/s: bound of the flat prior on the start's linear speed (no ``<prior speed>``)."""
SPIN_BOUND = 50.0
"""rad/s: bound of the flat prior on the start's spin (no ``<prior spin>``); a ball of 5 cm rolling
at 2.5 m/s spins at 50 rad/s."""
BOUND_SOFTNESS = 0.05
"""Beyond a flat prior's bound the residual grows by 1 per this fraction of the bound."""
FEASIBILITY_MARGIN = 0.003
"""Metres: a start whose source overlaps another object by more than this is infeasible (resting
contact overlaps by the contact model's fraction of a millimetre)."""


@dataclass(frozen=True)
class PosteriorSettings:
    """The resolved ``<prior>`` and ``<observation>`` (None: flat prior within the bounds).

    Attributes:
        sigma, angle_sigma: observation noise (m, rad).
        speed, spin, tilt: prior standard deviations (m/s, rad/s, rad), or None.
        speed_bound, spin_bound: bounds of the flat priors (m/s, rad/s).
    """

    sigma: float = DEFAULT_SIGMA
    angle_sigma: float = DEFAULT_ANGLE_SIGMA
    speed: float | None = None
    spin: float | None = None
    tilt: float | None = None
    speed_bound: float = SPEED_BOUND
    spin_bound: float = SPIN_BOUND

    @staticmethod
    def from_scene(scene) -> "PosteriorSettings":
        """The scene's ``<prior>`` and ``<observation>`` with the defaults filled in.

        A ``<heatmap sigma>`` given without ``<observation>`` is read as ``<observation sigma>``
        (scene-format spec, "Additions to version 1").
        """
        inf = scene.inference
        prior, obs = inf.prior, inf.observation
        sigma = DEFAULT_SIGMA
        if obs is not None and obs.sigma is not None:
            sigma = obs.sigma
        elif obs is None and inf.heatmap is not None:
            sigma = inf.heatmap.sigma
        out = PosteriorSettings(
            sigma=float(sigma),
            angle_sigma=float(obs.angle_sigma) if obs is not None and obs.angle_sigma is not None
            else DEFAULT_ANGLE_SIGMA,
            speed=None if prior is None or prior.speed is None else float(prior.speed),
            spin=None if prior is None or prior.spin is None else float(prior.spin),
            tilt=None if prior is None or prior.tilt is None else float(prior.tilt))
        out.check()
        return out

    def check(self) -> None:
        """One-line InferenceError for a non-positive or non-finite value."""
        for name in ("sigma", "angle_sigma", "speed", "spin", "tilt", "speed_bound", "spin_bound"):
            v = getattr(self, name)
            if v is None and name in ("speed", "spin", "tilt"):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise InferenceError(f"{name.replace('_', '-')} must be a positive number, got {v!r}")

    def to_json(self) -> dict:
        """``result.json``'s ``prior`` and ``observation``: every value in force, flat ones as null
        beside their bounds."""
        return {"observation": {"sigma": self.sigma, "angle_sigma": self.angle_sigma},
                "prior": {"speed": self.speed, "spin": self.spin, "tilt": self.tilt,
                          "position": "uniform in the start area",
                          "speed_bound": None if self.speed is not None else self.speed_bound,
                          "spin_bound": None if self.spin is not None else self.spin_bound}}


class Posterior:
    """Negative log posterior of an ``InferenceProblem``'s parameters, as least-squares residuals.

    Args:
        problem: the spheres backend's ``InferenceProblem`` (rollouts, layout, target, penalties).
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
        t = problem.target
        self._target_origin = torch.as_tensor(t.position, dtype=dt)
        self._target_q = normalize_quat(torch.as_tensor(t.orientation, dtype=dt))
        self._target_com = self._target_origin + quat_rotate(self._target_q, world.com[problem.source])

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

    @property
    def num_observed(self) -> int:
        """Observation residuals per candidate (6 for a pose, 3 for a position, 1 for ADD, plus
        3 per target velocity)."""
        p = self.problem
        n = {"pose": 6, "position": 3, "add": 1}[p.loss_kind]
        return n + 3 * (p.target.linear_velocity is not None) + 3 * (p.target.angular_velocity is not None)

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
        """Residuals of the observed end at the compared record, and the scene's loss there.

        Args:
            traj: Trajectory of the candidates, states (T, B, N, ...).
        Returns:
            residuals (B, M_obs) and the scene's per-record loss at the compared record (B,) in
            metres (``InferenceProblem.loss_of_trajectory`` without penalties).
        """
        from dejaview.losses import LOSSES
        from dejaview.losses.trajectory import nearest_record

        p, s = self.problem, self.settings
        body, world, st = p.source, p.world, traj.states
        fixed = None  # the one record compared, where it does not depend on the candidate
        if p.target.time is not None:
            fixed = nearest_record(traj, p.target.time)
        elif p.evaluate != "best":
            fixed = st.position.shape[0] - 1
        if fixed is None and p.loss_kind == "pose":  # evaluate=best: each candidate's record first,
            k = self._best_pose_records(st)  # by a cheap chi-square, then its residuals alone
            b = torch.arange(k.shape[0])
            st = State(*(t[k, b].unsqueeze(0) for t in st.tensors()))
            fixed = 0
        elif fixed is not None:  # the residuals of that record only (the same numbers, T times cheaper)
            st = State(*(t[fixed:fixed + 1] for t in st.tensors()))
        pos, q = st.position[..., body, :], st.orientation[..., body, :]  # (T, B, 3/4)
        if p.loss_kind == "position":
            origin = pos - quat_rotate(q, world.com[body].expand_as(pos))
            parts = [(origin - self._target_origin) / s.sigma]
        elif p.loss_kind == "add":
            add = LOSSES["add"](world, body, st, self._target_origin, self._target_q, points=p.points)
            parts = [add.unsqueeze(-1) / s.sigma]
        else:
            rel = quat_multiply(q, quat_conjugate(self._target_q).expand_as(q))
            parts = [(pos - self._target_com) / s.sigma, quat_to_rotvec(rel) / s.angle_sigma]
        r = torch.cat(parts + self._velocity_residuals(st), -1)  # (T, B, M)
        b = torch.arange(r.shape[1])
        if fixed is not None:
            k = torch.zeros_like(b)
        else:  # evaluate="best": the record that fits best, per candidate
            k = (r.detach() ** 2).sum(-1).argmin(0)
        with torch.no_grad():  # the scene's loss at the compared record only: (1, B, N, ...) states
            at = State(*(t[k, b].unsqueeze(0) for t in st.tensors()))
            loss = LOSSES[p.loss_kind](world, body, at, self._target_origin, self._target_q,
                                       orientation_weight=p.orientation_weight, points=p.points)[0]
        return r[k, b], loss

    def _velocity_residuals(self, st) -> list[torch.Tensor]:
        """Residuals (T, B, 3) of the source's velocities against the target's, where the target
        gives them (linear, then angular), at states (T, B, N, ...)."""
        from dejaview.losses.trajectory import DEFAULT_VELOCITY_WEIGHT

        p, s = self.problem, self.settings
        out = []
        for target, field, sd in ((p.target.linear_velocity, "linear_velocity", s.sigma),
                                  (p.target.angular_velocity, "angular_velocity", s.angle_sigma)):
            if target is not None:
                v = torch.as_tensor(target, dtype=p.world.dtype)
                out.append(DEFAULT_VELOCITY_WEIGHT * (getattr(st, field)[..., p.source, :] - v) / sd)
        return out

    def _best_pose_records(self, st) -> torch.Tensor:
        """(B,) index of the record (of states (T, B, N, ...)) whose pose residuals' chi-square
        is least, per candidate: the pose loss's residuals squared and summed, the orientation's
        by its geodesic angle (the length of its rotation vector, without computing those)."""
        p, s = self.problem, self.settings
        with torch.no_grad():
            pos, q = st.position[..., p.source, :], st.orientation[..., p.source, :]
            chi2 = (((pos - self._target_com) / s.sigma) ** 2).sum(-1)
            chi2 = chi2 + (geodesic_angle(self._target_q.expand_as(q), q) / s.angle_sigma) ** 2
            for part in self._velocity_residuals(st):
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
                parts.append(torch.relu(norm - bound) / (BOUND_SOFTNESS * bound))
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
        path = "phi" if 13 * bodies <= self.variants * self.num_observed else "adjoint"
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


def feasibility_check(scene, problem, margin: float = FEASIBILITY_MARGIN, collision=None):
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
