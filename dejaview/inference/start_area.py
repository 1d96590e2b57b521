"""Can the start area hold the source? Checked by ``solve``, the heatmaps and the service before
any search, sampling or heatmap work.

A start is a past only where the source, placed there, overlaps no other object by more than
``PosteriorSettings.feasibility_margin`` (``posterior.feasibility_check``). Where no start the prior allows is
free, every candidate costs infinity and a solve could only end with "every evaluation gave a
non-finite loss"; ``check_start_area`` finds that out first and says why in one line, as
``dejaview validate`` does for the given poses::

    box_in_desk.xml:21: <start-area> (-0.2, -0.1, 0.7233) to (0.2, 0.1, 0.7233) cannot hold 'src':
    everywhere in it 'src' and 'desk' interpenetrate, by 0.0267 m at the shallowest start found (more
    than the 0.003 m accepted as resting contact)

The starts the prior allows: positions in the box the parameter layout keeps them in
(``backends.params.layout_from_scene``: the start area, an axis without width fixed; the pose's
position, clamped into the area, where ``<optimize position>`` is false), at the ``<pose>``
orientation, or at any orientation where ``<optimize orientation>`` is true (a ``<prior tilt>`` is
a normal density on all of SO(3)). A free position without a start area is unbounded: nothing
to check. The box must lie within the bounds every backend's positions are kept in
(``scene.bounds.MAX_LENGTH``, which the reader enforces on scene files; scenes built in Python
meet it here).

The search (``_search``), on the exact geometry (``geometry.collision``, python-fcl):

1. the scene's own start, then the box's centre and ``StartAreaParams.draws`` random starts in it (random
   orientations where free): the first free one ends the check (every bundled scene's own start
   is free: one query);
2. a best-first branch and bound over the box: each cell's centre is tried (with ``StartAreaParams.orientations``
   random orientations where free), and the cell is settled when a lower bound of the depth
   there, minus the cell's half-diagonal, exceeds the margin (the depth of a translated solid
   changes no faster than the translation); else it is halved along its longest axis. The
   bound is the depth at the centre for a fixed orientation and, for a free one, the depth of
   the largest ball about the source's origin that lies inside it (``inner_radius``), which
   every orientation contains.

Every cell settled: the area cannot hold the source ("everywhere in it"). ``StartAreaParams.budget`` placements
tried without a free one and without settling every cell (a free orientation of a source whose
origin lies outside it, like a mug's, gives no bound; an overlap everywhere only a little past
the margin needs very small cells): the area is refused too, and the message says how many starts
were tried rather than "everywhere". The solve's own search draws fewer starts (64-256 screened
from the same prior, then CMA-ES, which cannot move from a population that all costs infinity).
"""

from __future__ import annotations

import heapq
import math

import numpy as np

from dejaview.errors import StartAreaError
from dejaview.inference.params import StartAreaParams
from dejaview.inference.posterior import PosteriorSettings
from dejaview.scene import bounds

def check_start_area(scene, collision=None, margin: float = PosteriorSettings.feasibility_margin):
    """Refuse a start area that cannot hold the source (module docstring).

    Args:
        scene: a Scene with an ``<inference>`` section.
        collision: a ``SceneCollision`` of the scene to reuse (built here if None and needed).
        margin: overlap (m) accepted as resting contact, the solve's.
    Returns:
        the ``SceneCollision`` used (for the solve's feasibility test), or None where nothing needed
        one (a free position without a start area).
    Raises:
        StartAreaError: one line naming the start area, the source, the objects and the depth (or
            the coordinate beyond the bounds).
    """
    from dejaview.backends.params import layout_from_scene

    inf = scene.inference
    layout = layout_from_scene(scene)
    area = inf.start_area
    where = _where(scene)
    if area is not None:
        corners = np.array([area.min, area.max], dtype=np.float64)
        if not np.all(np.isfinite(corners)):
            raise _error(where, f"{_box(corners[0], corners[1])} cannot hold {inf.source!r}: its "
                                       f"corners are not finite")
        i, axis = np.unravel_index(int(np.argmax(np.abs(corners))), corners.shape)
        if abs(corners[i, axis]) > bounds.MAX_LENGTH:
            raise _error(where, f"{_box(corners[0], corners[1])} cannot hold {inf.source!r}: it "
                                       f"reaches {'xyz'[axis]} = {corners[i, axis]:g} m, beyond the bounds "
                                       f"of every backend (|x|, |y|, |z| up to {bounds.MAX_LENGTH:g} m)")
    if layout.free["position"] and layout.position_axes and layout.lo is None:
        return collision  # a free position without a start area: unbounded
    if layout.free["position"] and layout.lo is not None:
        lo, hi = (layout.lo.double().numpy().copy(), layout.hi.double().numpy().copy())
    else:
        lo = hi = layout.base_position.double().numpy().copy()
    if collision is None:
        from dejaview.geometry.collision import SceneCollision

        collision = SceneCollision(scene)
    found = _search(collision, inf.source, lo, hi, layout.base_position.double().numpy(),
                    layout.base_orientation.double().numpy(), bool(layout.free["orientation"]), margin)
    if found is not None:
        raise _error(where, _message(inf.source, lo, hi, bool(layout.free["orientation"]), margin,
                                            *found))
    return collision


def _search(collision, source: str, lo: np.ndarray, hi: np.ndarray, guess: np.ndarray, q0: np.ndarray,
            free_orientation: bool, margin: float):
    """None as soon as a free start is found; else ``(certified, tried, least depth, object ids)``:
    every cell settled (``certified``) or ``StartAreaParams.budget`` placements tried without a free one. Each
    placement is decided as the solve decides its candidates (``penetration(decide_only=True)``,
    whose depth is then a lower bound); the depth reported is the full one at the shallowest."""
    rng = np.random.default_rng(0)
    tried = 0
    names: dict[str, int] = {}
    seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (depth bounds, positions, orientations)

    def orientations(n: int, per: int) -> np.ndarray:
        """(n, per, 4): the pose's orientation first, then random ones where free."""
        quats = np.broadcast_to(q0, (n, per, 4)).copy()
        if free_orientation and per > 1:
            quats[:, 1:] = _random_quaternions(rng, n * (per - 1)).reshape(n, per - 1, 4)
        return quats

    def place(positions: np.ndarray, quats: np.ndarray) -> np.ndarray | None:
        """A lower bound of the depth at each position (n, 3) at the shallowest of its orientations
        ``quats`` (n, per, 4): (n,); None where one start is free."""
        nonlocal tried
        n, per = quats.shape[:2]
        at = np.repeat(positions, per, axis=0)
        hit, depth, other = collision.penetration(source, at, quats.reshape(-1, 4), margin=margin,
                                                  decide_only=True)
        tried += n * per
        if not bool(np.all(hit)):
            return None
        seen.append((depth, at, quats.reshape(-1, 4)))
        best = depth.reshape(n, per).argmin(axis=1) + per * np.arange(n)
        for name in (other[j] for j in best):  # what the shallowest orientation at each position hits
            names[name] = names.get(name, 0) + 1
        return depth[best]

    per = 1 + StartAreaParams.orientations if free_orientation else 1
    # 1. the scene's own start, the centre, random starts (each at a random orientation where free)
    if place(guess[None], q0[None, None]) is None:
        return None
    draws = lo + (hi - lo) * rng.random((StartAreaParams.draws + 1, 3))
    draws[0] = 0.5 * (lo + hi)
    quats = np.broadcast_to(q0, (StartAreaParams.draws + 1, 1, 4)).copy()
    if free_orientation:
        quats[1:, 0] = _random_quaternions(rng, StartAreaParams.draws)
    if place(draws, quats) is None:
        return None
    # 2. best-first branch and bound over the box
    radius = collision.inner_radius(source) if free_orientation else 0.0
    heap = [(-math.inf, 0, 0.5 * (lo + hi), 0.5 * (hi - lo))]
    count = 1
    while heap and tried < StartAreaParams.budget:
        cells = [heapq.heappop(heap) for _ in range(min(StartAreaParams.batch, len(heap)))]
        centres = np.array([c[2] for c in cells])
        halves = np.array([c[3] for c in cells])
        depth = place(centres, orientations(len(cells), per))
        if depth is None:
            return None
        if not free_orientation:
            bound = depth
        elif radius > 0:
            bound, _ = collision.ball_penetration(source, centres, radius)
        else:
            bound = np.zeros(len(cells))
        reach = np.linalg.norm(halves, axis=1)
        for k in range(len(cells)):
            key = bound[k] - reach[k]
            if key > margin:
                continue  # no start in this cell is free
            axis = int(np.argmax(halves[k]))
            half = halves[k].copy()
            half[axis] *= 0.5
            for sign in (-1.0, 1.0):
                centre = centres[k].copy()
                centre[axis] += sign * half[axis]
                heapq.heappush(heap, (key, count, centre, half))
                count += 1
    # the full depth of the placements whose bounds are least: the shallowest found
    bounds_, at, quats = (np.concatenate(part) for part in zip(*seen))
    few = np.argsort(bounds_, kind="stable")[:StartAreaParams.recheck]
    _, depth, other = collision.penetration(source, at[few], quats[few], margin=margin)
    i = int(depth.argmin())
    ranked = sorted(names, key=lambda n: -names[n])
    if other[i] is not None:
        ranked = [other[i]] + [n for n in ranked if n != other[i]]
    return not heap, tried, float(depth[i]), ranked


def _message(source: str, lo, hi, free_orientation: bool, margin: float, certified: bool, tried: int,
             least: float, names: list[str]) -> str:
    shown = [repr(n) for n in names[:StartAreaParams.named]]
    if len(names) > StartAreaParams.named:
        shown.append(f"{len(names) - StartAreaParams.named} other object(s)")
    if len(shown) == 1:
        pair = f"{source!r} and {shown[0]} interpenetrate"
    else:
        pair = f"{source!r} interpenetrates {', '.join(shown[:-1])} or {shown[-1]}"
    point = bool(np.array_equal(lo, hi))
    box = f"the start {_box(lo, hi)}" if point else _box(lo, hi)
    turned = ", at any orientation," if free_orientation else ""
    accepted = f"more than the {margin:g} m accepted as resting contact"
    if certified:
        return (f"{box} cannot hold {source!r}: {'there' if point else 'everywhere in it'}{turned} {pair}, "
                f"by {least:.4f} m at the shallowest start found ({accepted})")
    how = " (at random orientations)" if free_orientation else ""
    return (f"{box} cannot hold {source!r} at any of the {tried} starts tried{'' if point else ' in it'}{how}: "
            f"at each {pair}, by {least:.4f} m at the shallowest ({accepted})")


def _box(lo, hi) -> str:
    fmt = lambda v: "(" + ", ".join(f"{float(x):g}" for x in v) + ")"  # noqa: E731
    return fmt(lo) if np.array_equal(lo, hi) else f"{fmt(lo)} to {fmt(hi)}"


def _where(scene) -> tuple[str, str | None, int | None]:
    """(element, file, line) the error points at: the start area, else the source's pose."""
    inf = scene.inference
    file = str(scene.path) if scene.path is not None else None
    if inf.start_area is not None:
        return "start-area", file, inf.start_area.line
    line = next((o.line for o in scene.objects if o.id == inf.source), None)
    return "pose", file, line


def _error(where, reason: str) -> StartAreaError:
    element, file, line = where
    return StartAreaError(reason, file=file, line=line, element=element)


def _random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4) unit quaternions uniform on SO(3), w x y z."""
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)
