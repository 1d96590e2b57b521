"""Symmetries of a scene's dynamics, and the sampler's move along them.

A scene whose static shapes are all horizontal planes (normal along z), with
gravity along z and the source as its only movable body, looks the same after
a horizontal translation and after a rotation about a vertical axis. Its
dynamics are equivariant: the rollout of a start moved by such a motion g is
the start's rollout moved by g (the contacts, friction and restitution are
isotropic, and so is every physics variant of ``<model-uncertainty>``). On a
floor, a box thrown from 10 cm further left lands 10 cm further left, turned
the same way.

The group acts on the source's start (``FloorSymmetry.act``): g = (theta, t)
turns its orientation and velocities by theta about the vertical axis through
its start position and moves that position by t (horizontal, along the free
position axes only). The two commute, so g is an element of the abelian group
SO(2) x R^2 and (theta, t) composes by addition. Its rollout is the start's
rollout turned by theta about the same axis and moved by t
(``FloorSymmetry.act_trajectory``).

So for a particle x whose rollout is known, the posterior density of every g x
costs no rollout: its trajectory is g applied to x's. In coordinates (r, g)
(``FloorSymmetry.coordinates``: g the start's heading psi, from q = T(psi) S
with T a turn about z and S a swing about a horizontal axis, and its horizontal
position; r the swing, the velocities turned back by psi, and the rest) the
group adds to g and leaves r alone, and ``orbit_walk`` moves the particles in
both (``dejaview.inference.sampling`` calls it):

- along the orbit: conditional importance sampling (Andrieu, Lee and Vihola
  2018) of g: ``SamplerParams.orbit_draws`` motions around the g that carries x's end onto the
  observed end (position and heading; the spread the tempered observation
  noise times ``SamplerParams.orbit_width``), each a turn drawn about the vertical through the
  end point rather than the start (an end a metre away would otherwise move
  by a metre times the turn) plus a normal translation, the current g among
  them, one drawn by the weights ``pi(r, g) / k(g)``, pi the tempered
  density in (r, g), i.e. at g x times ``|det dx/d(r, g)|`` (the start area's
  logit, the rotation vector's Haar factor);
- across orbits: a symmetric step in r (a normal step with the population's
  covariance of r, or a differential-evolution step), accepted with
  probability ``Z(r') / Z(r)``, Z the orbit's integral of pi over g, both
  estimated by the importance sampling above (pseudo-marginal Metropolis-
  Hastings, Andrieu and Roberts 2009: exact for any number of draws), then g
  drawn on the orbit it lands on.

Both leave the tempered posterior invariant up to the engine's rounding: the
moved rollout is g times x's rollout, not a fresh one
(``tests/inference/test_symmetry.py`` checks that both agree to 1e-9 and that
the moves keep a known target).

Why: the end's horizontal position and heading are the observation's most
precise numbers, and where a thrown box ends after two tumbles moves by
centimetres with millimetres of its start, so a walk in the start is almost
always refused for an end a few centimetres or degrees off. Across orbits
those are aligned anew for every proposal, and the walk only has to keep
what the motions cannot change (which face the box lands on, whether its
start fits in the start area). Measured on the calibration bench:
docs/benchmarks.md ("Symmetry moves").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dejaview.inference.params import SamplerParams
from dejaview.inference.reference import log_density, log_haar
from dejaview.sim.rotation import quat_multiply, quat_rotate, quat_to_rotvec, rotvec_to_quat
from dejaview.sim.state import State, Trajectory

def _rotation_z(theta: torch.Tensor) -> torch.Tensor:
    """(B, 4) quaternions of rotations by theta (B,) about z."""
    h = 0.5 * theta
    z = torch.zeros_like(theta)
    return torch.stack([torch.cos(h), z, z, torch.sin(h)], -1)


def _turn(v: torch.Tensor, theta: torch.Tensor, bodies: bool = False) -> torch.Tensor:
    """Vectors v (..., B, 3) (``bodies``: (..., B, N, 3)) turned by theta (B,) about z."""
    c, s = torch.cos(theta), torch.sin(theta)
    if bodies:
        c, s = c[:, None], s[:, None]
    x, y = v[..., 0], v[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, v[..., 2]], -1)


@dataclass(frozen=True)
class FloorSymmetry:
    """The motions of a scene whose dynamics are equivariant (module docstring).

    Attributes:
        axes: free position axes (0: x, 1: y) the start may move along.
        rotate: whether the start may turn about the vertical (orientation free, and every
            fixed velocity vertical).
    """

    axes: tuple[int, ...]
    rotate: bool
    width: float = SamplerParams.orbit_width
    """The proposal's spread over the tempered observation noise (``spreads``)."""

    @staticmethod
    def of(post, width: float = SamplerParams.orbit_width) -> "FloorSymmetry | None":
        """The symmetry of ``post``'s scene (a ``Posterior``), or None where it has none (another
        movable body, a static shape that is not a horizontal plane, gravity not vertical, a
        position free in per-candidate boxes) or where the likelihood reads every record of each
        rollout (a moving target without a time under ``evaluate="best"``, a ``<penalty>``): the
        moves would carry every record of every candidate motion."""
        problem, lay = getattr(post, "problem", None), post.layout
        world = getattr(problem, "world", None)
        if world is None:  # not a simulated scene's posterior
            return None
        if problem.penalties or any(s.step is None for s in post.sightings):
            return None
        rounding = 1e-12  # vertical or horizontal up to the rounding of a rotation built from z
        if world.mass.shape[0] != 1 or float(world.gravity[:2].abs().max()) > rounding:
            return None
        for shape in world.statics:
            if shape.kind != "plane" or float((shape.rotation[:2, 2]).abs().max()) > rounding:
                return None
        if lay.lo is not None and lay.lo.dim() != 1:
            return None
        axes = tuple(a for a in (0, 1) if lay.free["position"] and a in lay.position_axes)
        if lay.lo is not None:  # an axis of zero width is not free; keep those with room
            axes = tuple(a for a in axes if float(lay.hi[a] - lay.lo[a]) > 0)
        rotate = bool(lay.free["orientation"]
                      and (lay.free["linear_velocity"] or float(lay.base_linear[:2].abs().max()) == 0)
                      and (lay.free["angular_velocity"] or float(lay.base_angular[:2].abs().max()) == 0))
        if not axes and not rotate:
            return None
        return FloorSymmetry(axes=axes, rotate=rotate, width=width)

    def act(self, lay, x: torch.Tensor, theta: torch.Tensor, t: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor]:
        """Parameters of the starts g x (B, P), g = (theta (B,), t (B, 2)), and ``log |d(g x)/dx|``
        (B,) (``-inf`` where g x leaves the start area or x's rotation vector is longer than pi,
        the branch on which the action is one-to-one).

        Args:
            lay: the ParameterLayout of x.
            x: (B, P) parameters; theta: (B,) radians (0 where ``rotate`` is False);
            t: (B, 2) metres along x and y (0 along an axis not in ``axes``).
        """
        y = x.clone()
        log_jac = torch.zeros(x.shape[0], dtype=x.dtype)
        cols = lay.block_slice("position")
        for j, a in enumerate(lay.position_axes if lay.free["position"] else ()):
            if a not in self.axes:
                continue
            c = cols.start + j
            if lay.lo is None:
                y[:, c] = x[:, c] + t[:, a] / lay.scale["position"]
                continue
            width = lay.hi[a] - lay.lo[a]
            f = torch.sigmoid(x[:, c]) + t[:, a] / width
            inside = (f > 0) & (f < 1)
            f = torch.where(inside, f, torch.full_like(f, 0.5))
            y[:, c] = torch.logit(f)
            g0 = torch.sigmoid(x[:, c])
            log_jac = log_jac + torch.log(g0 * (1 - g0)) - torch.log(f * (1 - f))
            log_jac = torch.where(inside, log_jac, torch.full_like(log_jac, -math.inf))
        if self.rotate:
            cols = lay.block_slice("orientation")
            sc = lay.scale["orientation"]
            r = sc * x[:, cols]
            r2 = quat_to_rotvec(quat_multiply(_rotation_z(theta), rotvec_to_quat(r)))
            y[:, cols] = r2 / sc
            ok = r.norm(dim=-1) <= math.pi
            log_jac = log_jac + log_haar(r.norm(dim=-1)) - log_haar(r2.norm(dim=-1))
            log_jac = torch.where(ok, log_jac, torch.full_like(log_jac, -math.inf))
            for block in ("linear_velocity", "angular_velocity"):
                cols = lay.block_slice(block)
                if cols.stop > cols.start:
                    y[:, cols] = _turn(x[:, cols], theta)
        return y, log_jac

    def act_trajectory(self, traj: Trajectory, pivot: torch.Tensor, theta: torch.Tensor,
                       t: torch.Tensor) -> Trajectory:
        """The rollout (T, B, N, ...) of the starts g x, from x's rollout ``traj``: every state turned
        by theta (B,) about the vertical axis through ``pivot`` (B, 3) (x's start position) and
        moved by t (B, 2)."""
        st = traj.states
        shift = torch.cat([t, torch.zeros_like(t[:, :1])], -1)
        piv = pivot[:, None, :]  # (B, 1, 3) against positions (T, B, N, 3)
        position = _turn(st.position - piv, theta, bodies=True) + piv + shift[:, None, :]
        rot = _rotation_z(theta)[:, None, :].expand_as(st.orientation)
        moved = State(position=position, orientation=quat_multiply(rot, st.orientation),
                      linear_velocity=_turn(st.linear_velocity, theta, bodies=True),
                      angular_velocity=_turn(st.angular_velocity, theta, bodies=True))
        return Trajectory(moved, traj.steps, traj.dt)

    def aligning(self, post, traj: Trajectory, pivot: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The motion (theta (B,), t (B, 2)) that carries the end of x's rollout ``traj`` onto the
        observed end: the heading of the observed orientation (where the loss compares
        orientations), then the observed centre of mass (the origin for the ``position`` loss);
        and the arm (B, 3) from the turns' axis ``pivot`` (x's start position) to that end point.
        The rollout's last record stands for the compared one."""
        problem = post.problem
        b = problem.source
        st = traj.states
        com, q = st.position[-1, :, b], st.orientation[-1, :, b]  # (B, 3), (B, 4)
        theta = torch.zeros(com.shape[0], dtype=com.dtype)
        if self.rotate and problem.loss_kind != "position" and post._target_q is not None:
            d = quat_multiply(post._target_q.expand_as(q), torch.cat([q[:, :1], -q[:, 1:]], -1))
            theta = 2 * torch.atan2(d[:, 3], d[:, 0])
        if problem.loss_kind == "position" or post._target_com is None:
            point = com - quat_rotate(q, problem.world.com[b].expand_as(com))
            goal = post._target_origin
        else:
            point, goal = com, post._target_com
        arm = point - pivot
        moved = _turn(arm, theta) + pivot
        t = torch.zeros(com.shape[0], 2, dtype=com.dtype)
        for a in self.axes:
            t[:, a] = goal[a] - moved[:, a]
        return theta, t, arm

    def spreads(self, post, beta: float) -> tuple[float, float]:
        """The proposal's standard deviations (theta in radians, t in metres) at beta: the
        observation's noise over sqrt(beta) times ``width``, at most a half turn and the start
        area's extent. An unobserved heading (the ``position`` loss) keeps the prior's tilt."""
        s, lay = post.settings, post.layout
        b = max(beta, 1e-12)
        extent = (max(float(lay.hi[a] - lay.lo[a]) for a in self.axes) if lay.lo is not None and self.axes
                  else 10 * lay.scale["position"])
        sd_t = min(self.width * s.sigma / math.sqrt(b), extent)
        if post.problem.loss_kind == "position" or post._target_q is None:
            sd_theta = math.pi if s.tilt is None else min(s.tilt, math.pi)
        else:
            sd_theta = min(self.width * s.angle_sigma / math.sqrt(b), math.pi)
        return sd_theta, sd_t

    # ------------------------------------------------------------ section coordinates
    def coordinates(self, lay, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Coordinates (r, g) of parameters x (B, P) in which the group acts by adding to g alone.

        Returns:
            r (B, D): what the motions leave alone: the free position axes not in ``axes``, the
            orientation's swing (the rotation vector, horizontal, of S in q = T(psi) S, T a turn
            about z), the velocities turned back by psi; the blocks as they are without ``rotate``.
            g (B, G): the heading psi (radians, in (-pi, pi], where ``rotate``), then the start
            position along each of ``axes`` (metres).
            log_volume (B,): ``log |det dx/d(r, g)|`` up to a constant (``-inf`` where x's rotation
            vector is longer than pi, outside the branch on which the coordinates are one-to-one).
        """
        b = x.shape[0]
        dec = lay.decode(x)
        log_vol = torch.zeros(b, dtype=x.dtype)
        r_parts, g_parts = [], []
        cols = lay.block_slice("position")
        for j, a in enumerate(lay.position_axes if lay.free["position"] else ()):
            c = cols.start + j
            if a in self.axes:
                if lay.lo is not None:  # dx/dp = 1 / (width f (1 - f)), the width a constant
                    f = torch.sigmoid(x[:, c])
                    log_vol = log_vol - torch.log(f * (1 - f))
            else:
                r_parts.append(x[:, c:c + 1])
        if self.rotate:
            q = dec["orientation"]
            psi = torch.remainder(2 * torch.atan2(q[:, 3], q[:, 0]) + math.pi, 2 * math.pi) - math.pi
            swing = quat_to_rotvec(quat_multiply(_rotation_z(-psi), q))[:, :2]
            r_parts.append(swing)
            rvec = lay.scale["orientation"] * x[:, lay.block_slice("orientation")]
            a = swing.norm(dim=-1)
            small = a < 1e-6
            log_swing = torch.log(0.5 * torch.where(small, 1 - a * a / 6,
                                                    torch.sin(a) / torch.where(small, torch.ones_like(a), a)))
            log_vol = log_vol + log_swing - log_haar(rvec.norm(dim=-1))
            log_vol = torch.where(rvec.norm(dim=-1) <= math.pi, log_vol, torch.full_like(log_vol, -math.inf))
            for block in ("linear_velocity", "angular_velocity"):
                c = lay.block_slice(block)
                if c.stop > c.start:
                    r_parts.append(_turn(x[:, c], -psi))
            g_parts.append(psi[:, None])
        else:
            for block in ("orientation", "linear_velocity", "angular_velocity"):
                c = lay.block_slice(block)
                if c.stop > c.start:
                    r_parts.append(x[:, c])
        for a in self.axes:
            g_parts.append(dec["position"][:, a:a + 1])
        empty = x[:, :0]
        return (torch.cat(r_parts, -1) if r_parts else empty), torch.cat(g_parts, -1), log_vol

    def parameters(self, lay, r: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Parameters x (B, P) at coordinates (r, g) (``coordinates``), and (B,) whether they are
        valid (the position inside the start area, the swing's angle below pi)."""
        b = r.shape[0]
        x = torch.zeros(b, lay.size, dtype=r.dtype)
        ok = torch.ones(b, dtype=torch.bool)
        k = 0  # next column of r
        gi = 1 if self.rotate else 0
        cols = lay.block_slice("position")
        for j, a in enumerate(lay.position_axes if lay.free["position"] else ()):
            c = cols.start + j
            if a in self.axes:
                p = g[:, gi + self.axes.index(a)]
                if lay.lo is None:
                    x[:, c] = (p - lay.base_position[a]) / lay.scale["position"]
                else:
                    f = (p - lay.lo[a]) / (lay.hi[a] - lay.lo[a])
                    inside = (f > 0) & (f < 1)
                    ok &= inside
                    x[:, c] = torch.logit(torch.where(inside, f, torch.full_like(f, 0.5)))
            else:
                x[:, c] = r[:, k]
                k += 1
        if self.rotate:
            psi = g[:, 0]
            swing = r[:, k:k + 2]
            k += 2
            ok &= swing.norm(dim=-1) < math.pi
            s3 = torch.cat([swing, torch.zeros_like(swing[:, :1])], -1)
            q = quat_multiply(_rotation_z(psi), rotvec_to_quat(s3))
            q0 = lay.base_orientation.to(r.dtype).expand(b, 4)
            q0_inv = torch.cat([q0[:, :1], -q0[:, 1:]], -1)
            x[:, lay.block_slice("orientation")] = quat_to_rotvec(quat_multiply(q, q0_inv)) / lay.scale["orientation"]
            for block in ("linear_velocity", "angular_velocity"):
                c = lay.block_slice(block)
                if c.stop > c.start:
                    x[:, c] = _turn(r[:, k:k + 3], psi)
                    k += 3
        else:
            for block in ("orientation", "linear_velocity", "angular_velocity"):
                c = lay.block_slice(block)
                if c.stop > c.start:
                    x[:, c] = r[:, k:k + 3]
                    k += 3
        return x, ok

    def following(self, theta: torch.Tensor, centre: tuple, arm: torch.Tensor) -> torch.Tensor:
        """The translations (..., 2) that, after a turn by theta (...,) about the pivot, keep the
        end point where the motion ``centre`` = (theta_c (...,), t_c (..., 2)) puts it (along
        ``axes``; 0 along the others); ``arm`` (..., 3): from the pivot to the end point."""
        theta_c, t_c = centre
        shift = _turn(arm, theta_c) - _turn(arm, theta)
        t = torch.zeros_like(t_c)
        for a in self.axes:
            t[..., a] = t_c[..., a] + shift[..., a]
        return t

    def log_proposal(self, theta: torch.Tensor, t: torch.Tensor, centre: tuple, arm: torch.Tensor,
                     spread: tuple) -> torch.Tensor:
        """Log density (...,) of motions (theta (...,), t (..., 2)) under ``draw``'s proposal around
        the motion ``centre`` = (theta_c (...,), t_c (..., 2)) with end-point arm (..., 3)."""
        out = torch.zeros(theta.shape, dtype=theta.dtype)
        if self.rotate:
            k = torch.arange(-2, 3, dtype=theta.dtype) * (2 * math.pi)
            d = torch.remainder(theta - centre[0] + math.pi, 2 * math.pi) - math.pi
            z = (d[..., None] + k) / spread[0]
            out = out + torch.logsumexp(-0.5 * z * z, -1) - math.log(spread[0] * math.sqrt(2 * math.pi))
        mean = self.following(theta, centre, arm)
        for a in self.axes:
            z = (t[..., a] - mean[..., a]) / spread[1]
            out = out - 0.5 * z * z - math.log(spread[1] * math.sqrt(2 * math.pi))
        return out

    def draw(self, centre: tuple, arm: torch.Tensor, spread: tuple, m: int, gen: torch.Generator
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """m motions per particle around its motion ``centre`` = (theta_c (B,), t_c (B, 2)): theta
        (B, m) from a normal (wrapped) of sd ``spread[0]``; t (B, m, 2) turning about the end point
        (``following``, ``arm`` (B, 3)) plus a normal of sd ``spread[1]`` along ``axes``.

        Why about the end point: a turn about the start moves an end that lies a metre away by a
        metre times the angle, which the translations' own spread cannot undo, so the proposal
        would miss the observed end on every orbit whose body travels far."""
        b = centre[0].shape[0]
        z = torch.randn(b, m, 3, generator=gen, dtype=centre[0].dtype)
        theta = centre[0][:, None] + spread[0] * z[..., 0] if self.rotate else torch.zeros_like(z[..., 0])
        theta = torch.remainder(theta + math.pi, 2 * math.pi) - math.pi
        expand = (centre[0][:, None].expand(b, m), centre[1][:, None].expand(b, m, 2))
        t = self.following(theta, expand, arm[:, None].expand(b, m, 3))
        for a in self.axes:
            t[..., a] = t[..., a] + spread[1] * z[..., 1 + a]
        return theta, t


def compared_records(post, traj: Trajectory) -> Trajectory:
    """The records of ``traj`` that ``Posterior.observation_residuals`` reads: each sighting's and
    its rest window's (``FloorSymmetry.of`` leaves out the likelihoods that read every record),
    in step order; the last of them is the anchor's (the end, or the latest target time)."""
    from dejaview.losses.targets import record_index

    wanted = set()
    for s in post.sightings:
        wanted |= {s.step, *s.rest_steps}
    keep = sorted({record_index(traj.steps, k) for k in wanted})
    idx = torch.as_tensor(keep, dtype=torch.long)
    return Trajectory(State(*(t[idx] for t in traj.states.tensors())), traj.steps[idx], traj.dt)


def ends(post, x: torch.Tensor, known: tuple | None = None) -> list:
    """The compared records (``compared_records``) of the rollouts of x (B, P), one Trajectory
    (T', B, N, ...) per physics variant; ``known`` = (those of x, (B,) bool which of them hold):
    only the others are simulated."""
    if known is not None and bool(known[1].all()):
        return known[0]
    todo = torch.arange(x.shape[0]) if known is None else (~known[1]).nonzero().squeeze(-1)
    fresh = [compared_records(post, t) for t in post.trajectories(x[todo])]
    post.rollouts += int(todo.shape[0])
    if known is None:
        return fresh
    return assign(known[0], todo, fresh)


def assign(trajs: list, rows: torch.Tensor, new: list) -> list:
    """Copies of the trajectories ``trajs`` (T, B, N, ...) with the candidates ``rows`` (R,)
    replaced by ``new``'s (T, R, N, ...)."""
    out = []
    for old, fresh in zip(trajs, new):
        tensors = []
        for a, b in zip(old.states.tensors(), fresh.states.tensors()):
            a = a.clone()
            a[:, rows] = b
            tensors.append(a)
        out.append(Trajectory(State(*tensors), old.steps, old.dt))
    return out


def _orbit_weights(post, sym: FloorSymmetry, x: torch.Tensor, trajs: list, tempered, beta: float,
                   gen: torch.Generator, draws: int, keep_current: bool):
    """Importance sampling along the orbits of x (B, P), whose rollouts' compared records are
    ``trajs`` (``ends``).

    Returns (B, M) log weights ``log pi(r, g_m) - log k(g_m)`` of M motions g_m (the first the
    identity, x itself, where ``keep_current``), the M candidates' parameters (B, M, P), their log
    posterior densities (B, M), and the motions from x to them: theta (B, M), t (B, M, 2). The
    proposal k of a motion depends on x's orbit alone (its end point and heading move with x)."""
    lay = post.layout
    b = x.shape[0]
    pivot = lay.decode(x)["position"].detach()
    theta_c, t_c, arm = sym.aligning(post, trajs[0], pivot)
    spread = sym.spreads(post, beta)
    theta, t = sym.draw((theta_c, t_c), arm, spread, draws, gen)
    if keep_current:
        theta[:, 0], t[:, 0] = 0.0, 0.0
    m = theta.shape[1]
    rep = torch.arange(b).repeat_interleave(m)
    rel_theta, rel_t = theta.reshape(b * m), t.reshape(b * m, 2)
    y, log_jac = sym.act(lay, x[rep], rel_theta, rel_t)
    ok = torch.isfinite(log_jac)
    lp = torch.full((b * m,), -math.inf, dtype=x.dtype)
    if bool(ok.any()):
        moved = [sym.act_trajectory(tr.select(rep), pivot[rep], rel_theta, rel_t).select(ok) for tr in trajs]
        lp[ok] = log_density(post, y[ok], feasibility=False, trajs=moved)
    _, _, log_vol = sym.coordinates(lay, y)
    logw = tempered(y, lp) + log_vol - sym.log_proposal(rel_theta, rel_t, (theta_c[rep], t_c[rep]), arm[rep],
                                                        spread)
    logw = torch.where(ok & torch.isfinite(logw), logw, torch.full_like(logw, -math.inf))
    return logw.reshape(b, m), y.reshape(b, m, -1), lp.reshape(b, m), theta, t


def orbit_walk(post, sym: FloorSymmetry, x: torch.Tensor, tempered, beta: float, gen: torch.Generator,
               step: torch.Tensor | None = None, draws: int | None = None, known: tuple | None = None):
    """One move of the particles x (B, P) along and across the orbits (module docstring).

    With ``step`` None: a conditional importance-sampling move along each particle's orbit (its
    current motion one of ``draws``, the particle's new motion drawn by the weights). With
    ``step`` (B, D), an increment of the orbit coordinates r (``FloorSymmetry.coordinates``;
    symmetric in distribution, e.g. a normal step): the particle's orbit moves to r + step with
    probability ``Z(r + step) / Z(r)``, Z the orbit's integral of the tempered density,
    estimated by importance sampling over ``draws`` motions (pseudo-marginal: exact for any
    number of draws), then its motion is drawn on the orbit it is on. One rollout per particle
    and step, plus x's own unless ``known`` (``ends``) holds them.

    Args:
        tempered: ``(y (B, P), lp (B,)) -> (B,)`` log tempered target of parameters y whose log
            posterior density is lp.
        beta: the tempering exponent (sets the proposal's spread).
    Returns:
        (x (B, P), lp (B,) their log posterior densities, accepted (B,) bool: the orbit moved,
        or without ``step``, the particle did; the compared records of their rollouts (``ends``)).
    """
    lay = post.layout
    b = x.shape[0]
    draws = SamplerParams.orbit_draws if draws is None else draws
    r, g, _ = sym.coordinates(lay, x)
    base = ends(post, x, known)
    logw, ys, lps, rth, rt = _orbit_weights(post, sym, x, base, tempered, beta, gen, draws, keep_current=True)
    accept = torch.zeros(b, dtype=torch.bool)
    if step is not None:
        x_new, valid = sym.parameters(lay, r + step, g)
        logw_new = torch.full_like(logw, -math.inf)
        ys_new, lps_new, rth_new, rt_new = ys.clone(), lps.clone(), rth.clone(), rt.clone()
        reps = x.clone()
        if bool(valid.any()):
            idx = valid.nonzero().squeeze(-1)
            other = ends(post, x_new[idx])
            lw, yv, lv, th, tt = _orbit_weights(post, sym, x_new[idx], other, tempered, beta, gen, draws,
                                                keep_current=False)
            logw_new[idx], ys_new[idx], lps_new[idx], rth_new[idx], rt_new[idx] = lw, yv, lv, th, tt
            reps[idx] = x_new[idx]
        log_ratio = torch.logsumexp(logw_new, -1) - torch.logsumexp(logw, -1)
        u = torch.rand(b, generator=gen, dtype=x.dtype)
        accept = torch.isfinite(log_ratio) & (torch.log(u) < log_ratio)
        logw = torch.where(accept[:, None], logw_new, logw)
        ys = torch.where(accept[:, None, None], ys_new, ys)
        lps = torch.where(accept[:, None], lps_new, lps)
        rth = torch.where(accept[:, None], rth_new, rth)
        rt = torch.where(accept[:, None, None], rt_new, rt)
        if bool(accept.any()):  # the accepted orbits' representatives and rollouts
            idx = accept.nonzero().squeeze(-1)
            pos = torch.searchsorted(valid.nonzero().squeeze(-1), idx)
            base = assign(base, idx, [t.select(pos) for t in other])
        x = torch.where(accept[:, None], reps, x)
    pick = torch.multinomial(torch.softmax(logw, -1), 1, generator=gen).squeeze(-1)
    rows = torch.arange(b)
    moved = accept if step is not None else pick != 0
    pivot = lay.decode(x)["position"].detach()
    theta, t = rth[rows, pick], rt[rows, pick]
    out = [sym.act_trajectory(tr, pivot, theta, t) for tr in base]
    return ys[rows, pick], lps[rows, pick], moved, out
