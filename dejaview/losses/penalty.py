"""Contact penalties: how close two bodies come to touching during a rollout.

``contact_penalty(world, traj, a, b)`` is the smallest surface gap between the
sphere packings of ``a`` and ``b`` over all recorded states, clamped at zero
once they touch: ``relu(min_t min_ij |c_i - c_j| - r_i - r_j)``. Against a
fixed object (a static shape, not in the state) the gap of a sphere is the
shape's signed distance at its centre minus its radius; a box body meets a
plane or a static box with its corner spheres, as in the contacts
(``dejaview.sim.box_edges``). A moving robot's link (``dejaview.sim.motion``)
is met where it is at each record, as the rollout met it.

The minimum is hard: the gradient flows through the closest sphere pair at the
closest record only (a subgradient), and pulls that pair together. To keep
memory moderate for long rollouts and large packings, the search for the
closest pair runs without a graph, in chunks (at most ``chunk_elements``
sphere pairs at a time); only the chosen pair's distance is then recomputed
differentiably, so reverse mode stores a (B,)-sized graph and forward mode
carries tangents of (B,) values. Between two bodies the search is pruned
exactly by their bounding spheres: only records whose bounding-sphere gap is
below the pair gap at the record of closest bounding spheres are searched,
and none where the bodies touch there (the penalty is then 0 whichever pair
touches); the records left are screened in float32 and searched in float64
only where they come within ``SCREEN_TOLERANCE`` of the least screened gap.
The same penalties and gradients as a float64 search of every record, at a
fraction of its cost (``docs/benchmarks.md``, "Search").
"""

from __future__ import annotations

import math

import torch

from dejaview.errors import InferenceError
from dejaview.sim.box_edges import CORNER_KINDS, box_corners
from dejaview.sim.integrate import Trajectory
from dejaview.sim.rotation import quat_rotate

SCREEN_TOLERANCE = 1e-3
"""Metres: records whose float32 gap lies within this of the least one are searched in float64
(float32's error on these gaps is below 1e-4 m)."""
DEFAULT_CHUNK_ELEMENTS = 1 << 20
"""Sphere pairs the closest-pair search evaluates at once (~32 MiB of float64 temporaries)."""


def _points(c: torch.Tensor, position: torch.Tensor, orientation: torch.Tensor) -> torch.Tensor:
    """Body points c (S, 3) in the world: position (..., 3), orientation (..., 4) -> (..., S, 3)."""
    c = c.reshape(*([1] * (orientation.dim() - 1)), *c.shape)  # cross broadcasts, with equal ranks
    return position.unsqueeze(-2) + quat_rotate(orientation.unsqueeze(-2), c)


def _pick(x: torch.Tensor, t_idx: torch.Tensor) -> torch.Tensor:
    """x (T, B, ...) and per-candidate record indices t_idx (B,) -> (B, ...)."""
    idx = t_idx.reshape(1, -1, *([1] * (x.dim() - 2))).expand(1, *x.shape[1:])
    return x.gather(0, idx)[0]


def _resolve(world, name: str | int) -> tuple[str, int]:
    """('body', index) for a movable body, ('static', index) for a static shape."""
    if isinstance(name, int):
        return "body", name
    if name in world.names:
        return "body", world.names.index(name)
    for k, s in enumerate(world.statics):
        if s.name == name:
            return "static", k
    raise InferenceError(f"penalty names {name!r}, which is neither a movable body "
                         f"({', '.join(world.names)}) nor a fixed object "
                         f"({', '.join(s.name for s in world.statics) or 'none'})")


def contact_penalty(world, traj: Trajectory, body_a: str | int, body_b: str | int,
                    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS) -> torch.Tensor:
    """Smallest surface gap between two bodies over a rollout, zero once they touch.

    Args:
        world: the World.
        traj: Trajectory with states (T, B, N, ...).
        body_a, body_b: names (or movable-body indices); at most one may be a
            fixed object (a static shape of the world), in either position.
        chunk_elements: sphere-pair distances per chunk of the closest-pair search.
    Returns:
        (B,) gaps in metres, ``>= 0``.
    """
    kind_a, a = _resolve(world, body_a)
    kind_b, b = _resolve(world, body_b)
    if kind_a == "static":
        (kind_a, a), (kind_b, b) = (kind_b, b), (kind_a, a)
    if kind_a == "static":
        raise InferenceError(f"penalty between two fixed objects {body_a!r} and {body_b!r}")
    if kind_b == "body" and a == b:
        raise InferenceError(f"penalty between {body_a!r} and itself")
    pos, quat = traj.states.position, traj.states.orientation  # (T, B, N, 3), (T, B, N, 4)
    if kind_b == "body":
        gap = _body_body_gap(world, pos, quat, a, b, chunk_elements)
    else:
        gap = _body_static_gap(world, pos, quat, a, _poses(world, traj, world.statics[b]), chunk_elements)
    return torch.relu(gap)


def _poses(world, traj: Trajectory, static):
    """``posed(t)``: the static shape where it is at record t (a moving robot's link moves along its
    path, ``dejaview.sim.motion``: record t is at substep ``steps[t] * substeps``)."""
    if static.path is None:
        return lambda t: static
    substeps = [int(s) * world.substeps for s in traj.steps.tolist()]
    return lambda t: static.at(substeps[t])


def _running_argmin(gaps_of_chunk, n_records: int, per_record: int, chunk_elements: int):
    """Scan records in chunks: (best value (B,), record (B,), flat pair index (B,)), no graph."""
    chunk = max(1, chunk_elements // max(1, per_record))
    best = rec = pair = None
    for t0 in range(0, n_records, chunk):
        g = gaps_of_chunk(t0, min(n_records, t0 + chunk))  # (t, B, P)
        value, flat = g.permute(1, 0, 2).reshape(g.shape[1], -1).min(dim=-1)
        t_idx = flat // g.shape[2] + t0
        p_idx = flat % g.shape[2]
        if best is None:
            best, rec, pair = value, t_idx, p_idx
        else:
            better = value < best
            best = torch.where(better, value, best)
            rec = torch.where(better, t_idx, rec)
            pair = torch.where(better, p_idx, pair)
    return best, rec, pair


def _body_body_gap(world, pos, quat, a: int, b: int, chunk_elements: int) -> torch.Tensor:
    ra, rb = world.radii[a], world.radii[b]
    sb = rb.shape[0]
    # padding pairs get -inf reach, so an infinite gap
    reach = (ra[:, None] + rb[None, :]).masked_fill((world.mask[a][:, None] * world.mask[b][None, :]) <= 0,
                                                   -float("inf"))
    # the search only chooses indices: it runs on values without a graph
    pos_d, quat_d = pos.detach(), quat.detach()
    n_cand = pos.shape[1]

    def gaps(t, c, dtype=pos.dtype):
        """Sphere-pair gaps (K, Sa * Sb) at records t (K,) of candidates c (K,), in ``dtype``."""
        # relative to a's COM, |x|^2 + |y|^2 - 2 x.y stays accurate; the chosen pair is recomputed exactly
        pa, qa = pos_d[t, c, a].to(dtype), quat_d[t, c, a].to(dtype)
        pb, qb = pos_d[t, c, b].to(dtype), quat_d[t, c, b].to(dtype)
        ca = quat_rotate(qa.unsqueeze(-2), world.centers[a].to(dtype).unsqueeze(0))  # (K, Sa, 3)
        cb = quat_rotate(qb.unsqueeze(-2), world.centers[b].to(dtype).unsqueeze(0)) + (pb - pa).unsqueeze(-2)
        sq = ((ca * ca).sum(-1).unsqueeze(-1) + (cb * cb).sum(-1).unsqueeze(-2)
              - 2.0 * ca @ cb.transpose(-1, -2))  # (K, Sa, Sb) squared distances, one matmul
        return (sq.clamp(min=0.0).sqrt() - reach.to(dtype)).flatten(-2)

    def least(t, c, dtype=pos.dtype):
        """Least gap and its pair (K,) of each entry, in chunks of ``chunk_elements`` pairs."""
        per = max(1, chunk_elements // max(1, ra.shape[0] * sb))
        values, pairs = [], []
        for k0 in range(0, t.shape[0], per):
            v, p_ = gaps(t[k0:k0 + per], c[k0:k0 + per], dtype).min(-1)
            values.append(v)
            pairs.append(p_)
        return torch.cat(values), torch.cat(pairs)

    # Pruning, exact: the bounding spheres about the COMs bound every record's gap from below,
    # lb(t) = |x_a - x_b| - R_a - R_b. The gap at the record of the smallest lb is an upper
    # bound U of the minimum, so only records with lb(t) <= U can hold the closest pair.
    lb = torch.linalg.vector_norm(pos_d[:, :, a] - pos_d[:, :, b], dim=-1) - world.bound[a] - world.bound[b]
    cand = torch.arange(n_cand)
    t_star = lb.argmin(0)  # (B,)
    upper = gaps(t_star, cand).amin(-1)  # (B,)
    # A candidate whose bodies touch there (gap <= 0) has a penalty of exactly 0, relu(gap), with
    # a zero gradient: any touching pair gives that, so its search ends at once.
    keep = (lb <= upper.unsqueeze(0)) & (upper > 0).unsqueeze(0)
    keep[t_star, cand] = True  # each candidate keeps its record t*, a non-finite one that alone
    et, ec = keep.nonzero(as_tuple=True)  # (K,) records and candidates to search
    if pos.dtype == torch.float64 and et.shape[0] > n_cand:
        # screen the entries in float32 (faster; its gaps are off by far less than the tolerance) and search
        # exactly only those within SCREEN_TOLERANCE of their candidate's least screened gap
        v32, _ = least(et, ec, torch.float32)
        v32 = v32.to(pos.dtype)
        m32 = torch.full((n_cand,), math.inf, dtype=pos.dtype).scatter_reduce(0, ec, v32, "amin")
        near = (v32 <= m32[ec] + SCREEN_TOLERANCE) | (et == t_star[ec])
        et, ec = et[near], ec[near]
    ev, ep = least(et, ec)
    # per candidate, its entry of least gap (first record on ties, as a scan in time would pick)
    order = torch.argsort(ev, stable=True)
    order = order[torch.argsort(ec[order], stable=True)]
    first = torch.ones(order.shape[0], dtype=torch.bool)
    first[1:] = ec[order][1:] != ec[order][:-1]
    chosen = order[first]  # (B,), candidates in ascending order, each present once
    rec, pair = et[chosen], ep[chosen]
    i, j = pair // sb, pair % sb
    pa, qa = _pick(pos[:, :, a], rec), _pick(quat[:, :, a], rec)  # (B, 3), (B, 4)
    pb, qb = _pick(pos[:, :, b], rec), _pick(quat[:, :, b], rec)
    ca = pa + quat_rotate(qa, world.centers[a][i])
    cb = pb + quat_rotate(qb, world.centers[b][j])
    # the chosen spheres are distinct bodies' centres, never coincident while apart; the tiny
    # floor only keeps the gradient finite for a (clamped-away) exact overlap
    diff = ca - cb
    dist = torch.sqrt((diff * diff).sum(-1) + torch.finfo(pos.dtype).tiny)
    return dist - ra[i] - rb[j]


def _body_static_gap(world, pos, quat, a: int, posed, chunk_elements: int) -> torch.Tensor:
    # the spheres body a meets the static with: a box's corners against a plane or a static box
    # (dejaview.sim.box_edges, as the contacts), else its packing; ``posed(t)``: the static at record t
    static = posed(0)
    if world.box_bodies[a] and static.kind in CORNER_KINDS:
        centres, ra = (t[a] for t in box_corners(world.box_half))
        invalid = torch.zeros_like(ra, dtype=torch.bool)
    else:
        centres, ra, invalid = world.centers[a], world.radii[a], world.mask[a] <= 0
    far = torch.finfo(pos.dtype).max
    pos_d, quat_d = pos.detach(), quat.detach()

    moving = static.path is not None

    def gaps(t0, t1):
        ca = _points(centres, pos_d[t0:t1, :, a], quat_d[t0:t1, :, a])  # (t, B, Sa, 3)
        if moving:  # each record against the shape where it is then
            d = torch.stack([posed(t).distance(ca[t - t0])[0] for t in range(t0, t1)])
        else:
            d, _ = static.distance(ca)
        return (d - ra).masked_fill(invalid, far)

    _, rec, i = _running_argmin(gaps, pos.shape[0], ra.shape[0], chunk_elements)
    pa, qa = _pick(pos[:, :, a], rec), _pick(quat[:, :, a], rec)
    ca = pa + quat_rotate(qa, centres[i])
    if not moving:
        d, _ = static.distance(ca)
        return d - ra[i]
    d = torch.zeros_like(ra[i])
    for t in torch.unique(rec).tolist():  # each candidate against the shape at its own record
        sel = rec == t
        d = torch.where(sel, posed(t).distance(ca)[0], d)
    return d - ra[i]
