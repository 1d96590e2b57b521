"""The greedy lattice cover that packs a closed mesh with spheres (``SpherePacking.from_mesh``).

The mesh's inside is sampled on a regular lattice (``interior_lattice``); each
interior node is a candidate centre whose sphere may reach its distance to the
surface plus the tolerance; ``greedy_cover`` picks, one at a time, the candidate
covering the most nodes not yet covered.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from dejaview.errors import GeometryError
from dejaview.geometry import distance

# Automatic lattice: a trial with about _TRIAL_NODES interior nodes measures the
# work of the greedy cover; the final lattice aims at _COVER_WORK node visits
# with _MIN_NODES to _MAX_NODES interior nodes, _MAX_LATTICE_NODES in all.
_TRIAL_NODES = 20_000
_COVER_WORK = 20e6
_MIN_NODES = 20_000
_MAX_NODES = 300_000
_MAX_LATTICE_NODES = 6_000_000


def _lattice(triangles, solid, spacing):
    """Lattice centred on the mesh's bounding box (a node at its centre), one node
    layer outside on every side.

    Returns:
        origin (3,), shape (3,) tuple and inside (nx, ny, nz) bool.
    """
    lo, hi = solid.bounds
    shape = np.floor((hi - lo) / spacing).astype(np.int64) + 3
    shape += 1 - shape % 2  # odd counts put a node at the centre of symmetric shapes
    origin = 0.5 * (lo + hi) - 0.5 * (shape - 1) * spacing
    inside = distance.lattice_inside(triangles, origin, spacing, shape)
    return origin, tuple(int(n) for n in shape), inside


def interior_lattice(triangles, solid, resolution, tolerance, name):
    """Lattice for packing, at ``resolution`` or an automatic spacing.

    The automatic spacing balances accuracy against the cost of the greedy
    cover, which grows like (interior nodes) x (nodes per sphere), i.e. like
    spacing^-6: a coarse trial lattice measures that cost, and the spacing is
    chosen to meet ``_COVER_WORK``, within 20 000 to 300 000 interior nodes.
    Thin shapes that the trial lattice misses get finer trials.

    Returns:
        spacing, origin (3,), shape (3,), inside (nx, ny, nz) bool, and the signed
        distances (nx, ny, nz) if already computed, else None.
    """
    lo, hi = solid.bounds
    finest = (float(np.prod(hi - lo + 1e-9)) / _MAX_LATTICE_NODES) ** (1.0 / 3.0)
    if resolution is not None:
        spacing = float(resolution)
        if spacing < finest * 0.999:
            raise GeometryError(
                f"{name}: resolution {spacing:g} m needs more than {_MAX_LATTICE_NODES} "
                f"lattice nodes; use at least {finest:.3g} m"
            )
        origin, shape, inside = _lattice(triangles, solid, spacing)
        values = None
    else:
        spacing = max((float(solid.volume) / _TRIAL_NODES) ** (1.0 / 3.0), finest)
        for _ in range(4):
            origin, shape, inside = _lattice(triangles, solid, spacing)
            if inside.sum() >= _TRIAL_NODES // 4 or spacing / 2 < finest:
                break
            spacing /= 2
        count = int(inside.sum())
        values = None
        if count:
            values = distance.lattice_signed_distance(triangles, origin, spacing, shape,
                                                      band=spacing)
            reach = np.maximum(-values[inside] + tolerance, 0.0)
            # work(h) = sum over nodes of nodes per ball = work_coefficient / h^6
            work = float(np.sum(4.0 / 3.0 * np.pi * reach**3)) * spacing**3
            chosen = (work / _COVER_WORK) ** (1.0 / 6.0) if work > 0 else spacing
            coarsest = spacing * (count / _MIN_NODES) ** (1.0 / 3.0)
            finest_nodes = spacing * (count / _MAX_NODES) ** (1.0 / 3.0)
            chosen = max(min(chosen, coarsest), finest_nodes, finest)
            if abs(chosen - spacing) > 0.02 * spacing:
                spacing = chosen
                origin, shape, inside = _lattice(triangles, solid, spacing)
                values = None
    if not inside.any():
        raise GeometryError(
            f"{name}: no lattice node falls inside the mesh at spacing {spacing:g} m; "
            "the shape is thinner than that: pass a smaller resolution"
        )
    return spacing, origin, shape, inside, values


def greedy_cover(points: np.ndarray, reach: np.ndarray, spacing: float, budget: int,
                  min_radius: float, coverage: float | None, progress) -> np.ndarray:
    """Greedy maximum coverage of interior nodes by spheres centred on them.

    Args:
        points: (N, 3) interior nodes; each is a candidate centre and a node to cover.
        reach: (N,) largest allowed radius at each node.
        spacing: lattice spacing of ``points``.
        budget: most spheres.
        min_radius: candidates with a smaller reach are not used.
        coverage: stop once this fraction of nodes is covered (None: never).
        progress: optional callable(done, total).
    Returns:
        (M,) indices of the chosen centres, M <= budget, in insertion order.
    """
    tree = cKDTree(points)
    usable = np.flatnonzero((reach >= min_radius) & (reach > 0))
    gain = np.zeros(len(points), dtype=np.int64)
    if len(usable):
        gain[usable] = tree.query_ball_point(points[usable], reach[usable],
                                             return_length=True, workers=-1)
    widest = float(reach[usable].max()) if len(usable) else 0.0
    active = usable
    covered = np.zeros(len(points), dtype=bool)
    goal = len(points) if coverage is None else math.ceil(coverage * len(points))
    done = 0
    chosen: list[int] = []
    while len(chosen) < budget:
        best = int(np.argmax(gain))
        if gain[best] <= 0:
            break
        members = np.asarray(tree.query_ball_point(points[best], reach[best],
                                                   return_sorted=False), dtype=np.int64)
        fresh = members[~covered[members]]
        covered[fresh] = True
        done += len(fresh)
        chosen.append(best)
        if progress is not None:
            progress(len(chosen), budget)
        if done >= goal:
            break
        # only candidates whose ball meets the new one lose gain; small
        # neighbourhoods come from the tree, large ones from a scan
        span = reach[best] + widest
        if 4.2 * (span / spacing) ** 3 < len(active) / 2:
            near = np.asarray(tree.query_ball_point(points[best], span, return_sorted=False),
                              dtype=np.int64)
            near = near[gain[near] > 0]
        else:
            active = active[gain[active] > 0]
            near = active
        offset = points[near] - points[best]
        gap2 = np.einsum("ij,ij->i", offset, offset)
        near = near[gap2 <= (reach[near] + reach[best]) ** 2]
        if len(near):
            gain[near] -= cKDTree(points[fresh]).query_ball_point(
                points[near], reach[near], return_length=True
            )
    return np.asarray(chosen, dtype=np.int64)
