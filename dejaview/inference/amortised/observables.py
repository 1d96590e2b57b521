"""What an amortised posterior is conditioned on: the observations, as numbers a network reads.

For each of the scene's sightings (``Posterior.sightings``, in file order) the observation vector
holds what the likelihood compares (``dejaview.inference.posterior``):

- the source's object-frame origin (3, metres),
- where the likelihood compares an orientation (the target gives one, the loss reads it), its
  rotation as the first two columns of its matrix
  (6; continuous, unlike a quaternion's sign or a rotation vector's wrap at pi),
- the target's velocities where it gives them (3 each),
- where lying still is observed, the mean velocities over the rest window's parts
  (``REST_PARTS`` x 3 linear, then as many angular), which a resting target observes as zero.

``simulated`` reads them from rollouts and ``noisy`` adds the observation noise of
``PosteriorSettings`` (the same standard deviations the residuals divide by), so that training
pairs (start, noisy observation) are draws of the joint distribution whose conditional the flow
learns (neural posterior estimation). ``observed`` is the scene's own observation vector.

A sighting compared at its best record (a moving target without a time under
``evaluate="best"``) is read at the last record: the flow is then only a proposal, and the
importance weights (``dejaview.inference.amortised.answer``) judge it.
"""

from __future__ import annotations

import math

import torch

from dejaview.sim.rotation import normalize_quat, quat_rotate, quat_to_matrix


def _rot6(q: torch.Tensor) -> torch.Tensor:
    """(B, 6) first two columns of the rotation matrices of unit quaternions q (B, 4), w first."""
    m = quat_to_matrix(q)
    return torch.cat([m[..., 0], m[..., 1]], -1)


def _turns(post, sighting) -> bool:
    """Whether the likelihood compares the sighting's orientation: its target gives one and the
    scene's loss reads it (``pose`` or ``add``; a ``position`` loss compares the origin alone, and
    conditioning the flow on an orientation the likelihood ignores would make it sharper than the
    posterior: measured on the ramp's calibration, Pareto k-hat 0.66-1.31)."""
    return sighting.target.orientation is not None and post._kind(sighting) != "position"


def width(post) -> int:
    """D, the length of the observation vector of ``post``'s sightings."""
    from dejaview.losses.targets import REST_PARTS

    d = 0
    for s in post.sightings:
        t = s.target
        d += 3 + 6 * _turns(post, s)
        d += 3 * (t.linear_velocity is not None) + 3 * (t.angular_velocity is not None)
        d += 6 * REST_PARTS * bool(s.at_rest)
    return d


def simulated(post, traj) -> torch.Tensor:
    """(B, D) observation vectors of rollouts ``traj`` (a Trajectory (T, B, N, ...) recording what
    ``post``'s sightings read, ``Posterior.trajectories``), without noise."""
    from dejaview.losses.targets import record_index, rest_velocities

    p = post.problem
    body, st = p.source, traj.states
    com = p.world.com[body]
    parts = []
    for s in post.sightings:
        k = record_index(traj.steps, s.step) if s.step is not None else traj.steps.shape[0] - 1
        pos, q = st.position[k, :, body], normalize_quat(st.orientation[k, :, body])
        parts.append(pos - quat_rotate(q, com.expand_as(pos)))
        t = s.target
        if _turns(post, s):
            parts.append(_rot6(q))
        if t.linear_velocity is not None:
            parts.append(st.linear_velocity[k, :, body])
        if t.angular_velocity is not None:
            parts.append(st.angular_velocity[k, :, body])
        if s.at_rest:
            lin, ang = rest_velocities(traj, body, s)
            parts += [lin.flatten(1), ang.flatten(1)]
    return torch.cat(parts, -1)


def observed(post) -> torch.Tensor:
    """(D,) the scene's observation vector: its targets' poses and velocities, and zeros for the
    rest windows (lying still)."""
    from dejaview.losses.targets import REST_PARTS

    dt = torch.float64
    parts = []
    for s in post.sightings:
        t = s.target
        parts.append(torch.as_tensor(t.position, dtype=dt))
        if _turns(post, s):
            q = normalize_quat(torch.as_tensor(t.orientation, dtype=dt)).unsqueeze(0)
            parts.append(_rot6(q)[0])
        for v in (t.linear_velocity, t.angular_velocity):
            if v is not None:
                parts.append(torch.as_tensor(v, dtype=dt))
        if s.at_rest:
            parts.append(torch.zeros(6 * REST_PARTS, dtype=dt))
    return torch.cat(parts)


def with_target(post, y: torch.Tensor, position, orientation=None) -> torch.Tensor:
    """(D,) the observation vector y (D,) (``observed``) with the source seen elsewhere: the
    position (3,) and, where that sighting observes one, the orientation (4,) w x y z of the
    scene's anchor sighting (its untimed one, else its last: ``posterior._anchor``) replaced. The
    live service's cheap way to a new observation of a cached posterior (no scene, no world)."""
    from dejaview.inference.posterior import _anchor
    from dejaview.losses.targets import REST_PARTS

    anchor = _anchor(post.sightings)
    i = 0
    for s in post.sightings:
        t = s.target
        if s is anchor:
            break
        i += 3 + 6 * _turns(post, s) + 3 * (t.linear_velocity is not None)
        i += 3 * (t.angular_velocity is not None) + 6 * REST_PARTS * bool(s.at_rest)
    out = y.clone()
    out[i:i + 3] = torch.as_tensor(position, dtype=out.dtype)
    if orientation is not None and _turns(post, anchor):
        q = normalize_quat(torch.as_tensor(orientation, dtype=out.dtype)).unsqueeze(0)
        out[i + 3:i + 9] = _rot6(q)[0]
    return out


def noisy(post, y: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Observation vectors y (B, D) (``simulated``) with the observation noise added: each
    position by ``sigma``, each orientation turned about a random axis by a rotation vector with
    ``angle_sigma`` per component, velocities by the noise their residuals divide by
    (``sigma`` / ``angle_sigma`` over the velocity weight), rest means by ``rest_speed`` and
    ``rest_spin`` times sqrt(``REST_PARTS``)."""
    from dejaview.losses.targets import REST_PARTS
    from dejaview.losses.trajectory import DEFAULT_VELOCITY_WEIGHT

    s = post.settings
    out, i = [], 0
    b = y.shape[0]

    def normal(width_, sd):
        return sd * torch.randn(b, width_, generator=gen, dtype=y.dtype)

    for sg in post.sightings:
        t = sg.target
        out.append(y[:, i:i + 3] + normal(3, s.sigma))
        i += 3
        if _turns(post, sg):
            out.append(_turned(y[:, i:i + 6], normal(3, s.angle_sigma)))
            i += 6
        for v, sd in ((t.linear_velocity, s.sigma), (t.angular_velocity, s.angle_sigma)):
            if v is not None:
                out.append(y[:, i:i + 3] + normal(3, sd / DEFAULT_VELOCITY_WEIGHT))
                i += 3
        if sg.at_rest:
            n = 3 * REST_PARTS
            root = math.sqrt(REST_PARTS)
            out.append(y[:, i:i + n] + normal(n, s.rest_speed * root))
            out.append(y[:, i + n:i + 2 * n] + normal(n, s.rest_spin * root))
            i += 2 * n
    return torch.cat(out, -1)


def _turned(r6: torch.Tensor, rotvec: torch.Tensor) -> torch.Tensor:
    """Rotations r6 (B, 6) (``_rot6``) composed with small turns ``rotvec`` (B, 3) in the world
    frame (the residual's rotation vector is q * conj(q_goal): the simulated orientation relative
    to the observed one), as r6 again."""
    from dejaview.sim.rotation import rotvec_to_quat

    a, b = r6[:, :3], r6[:, 3:]
    c = torch.linalg.cross(a, b)
    m = torch.stack([a, b, c], -1)  # (B, 3, 3) columns
    out = quat_to_matrix(rotvec_to_quat(rotvec)) @ m
    return torch.cat([out[..., 0], out[..., 1]], -1)


__all__ = ["noisy", "observed", "simulated", "width", "with_target"]
