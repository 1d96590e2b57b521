"""Inside tests and signed distances from points and regular lattices to closed meshes.

trimesh answers these queries point by point through an R-tree, which takes
seconds for tens of thousands of points. Sphere packing and signed distance
grids need them on whole lattices, so this module does the bulk work with
vectorised numpy:

* inside/outside by the parity of crossings of vertical rays (one ray per
  lattice column, so a column of nodes costs one ray), with an edge rule that
  makes a ray through a shared edge or vertex count exactly once;
* exact distances only for nodes within a thin band around the surface, found
  per triangle from its bounding slab;
* everything further away takes the closest surface point of its nearest band
  node (a closest-point transform through ``scipy.ndimage.distance_transform_edt``)
  or of a neighbour if nearer; that can overestimate the true distance, by a
  small fraction of the spacing where it does.

Pointwise exact distances (for a few thousand points) use a k-d tree of
triangle centres to find candidate triangles.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

# Pairs processed per numpy batch: bounds temporary memory to ~100 MB.
_BATCH = 250_000


def triangle_array(mesh_or_triangles) -> np.ndarray:
    """(T, 3, 3) float64 triangles of a trimesh.Trimesh or triangle array, without
    zero-area ones (they change neither inside tests nor distances)."""
    if isinstance(mesh_or_triangles, trimesh.Trimesh):
        tri = np.asarray(mesh_or_triangles.triangles, dtype=np.float64)
    else:
        tri = np.asarray(mesh_or_triangles, dtype=np.float64).reshape(-1, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return tri[np.einsum("ij,ij->i", cross, cross) > 0.0]


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Enumerate ``counts[i]`` items for each i.

    Args:
        counts: (n,) non-negative integers.
    Returns:
        owner (sum,) index i of each item and local (sum,) its position 0..counts[i]-1.
    """
    counts = counts.astype(np.int64)
    owner = np.repeat(np.arange(len(counts)), counts)
    offsets = np.cumsum(counts) - counts
    local = np.arange(len(owner), dtype=np.int64) - offsets[owner]
    return owner, local


def _batches(counts: np.ndarray, budget: int = _BATCH):
    """Split (n,) item counts into consecutive index slices of about ``budget`` items each."""
    total = np.cumsum(counts)
    start = 0
    while start < len(counts):
        base = total[start - 1] if start else 0
        stop = int(np.searchsorted(total, base + budget, side="right"))
        stop = max(stop, start + 1)
        yield slice(start, stop)
        start = stop


def vertical_crossings(triangles, xy: np.ndarray, cell: float | None = None,
                       _retries: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Where vertical lines cross a closed mesh.

    Args:
        triangles: a trimesh.Trimesh or (T, 3, 3) triangles.
        xy: (M, 2) x y of the vertical lines.
        cell: bucket size used to match lines with triangles (default: about one
            line per bucket); any positive value gives the same answer.
    Returns:
        column (K,) index into ``xy`` of each crossing and z (K,) its height. Each
        line crosses a closed surface an even number of times.
    """
    tri = triangle_array(triangles)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0 or len(tri) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    lo, hi = xy.min(0), xy.max(0)
    if cell is None:
        extent = np.maximum(hi - lo, 1e-12)
        cell = float(np.sqrt(extent[0] * extent[1] / len(xy))) or float(extent.max())
        cell = max(cell, float(extent.max()) / 4096.0)
    ncell = np.floor((hi - lo) / cell).astype(np.int64) + 1
    cell_of = np.floor((xy - lo) / cell).astype(np.int64)
    cell_id = cell_of[:, 0] * ncell[1] + cell_of[:, 1]
    order = np.argsort(cell_id, kind="stable")
    per_cell = np.bincount(cell_id, minlength=int(ncell[0] * ncell[1]))
    cell_start = np.cumsum(per_cell) - per_cell

    t2 = tri[:, :, :2]
    tmin, tmax = t2.min(1), t2.max(1)
    keep = np.all(tmax >= lo, axis=1) & np.all(tmin <= hi, axis=1)
    tri, t2, tmin, tmax = tri[keep], t2[keep], tmin[keep], tmax[keep]
    c0 = np.clip(np.floor((tmin - lo) / cell).astype(np.int64), 0, ncell - 1)
    c1 = np.clip(np.floor((tmax - lo) / cell).astype(np.int64), 0, ncell - 1)
    span = c1 - c0 + 1
    per_tri = span[:, 0] * span[:, 1]

    # Per triangle and edge (a b, b c, c a; opposite vertex c, a, b): the edge put
    # in a canonical direction so both triangles of a shared edge compute
    # bit-identical edge functions, and the opposite vertex's side of it.
    corner = [(0, 1, 2), (1, 2, 0), (2, 0, 1)]
    edge_u, edge_d, edge_o = [], [], []
    for i, j, k in corner:
        u, v, o = t2[:, i], t2[:, j], t2[:, k]
        swap = (u[:, 0] > v[:, 0]) | ((u[:, 0] == v[:, 0]) & (u[:, 1] > v[:, 1]))
        cu = np.where(swap[:, None], v, u)
        cd = np.where(swap[:, None], u, v) - cu
        edge_u.append(cu)
        edge_d.append(cd)
        edge_o.append(cd[:, 0] * (o[:, 1] - cu[:, 1]) - cd[:, 1] * (o[:, 0] - cu[:, 0]))

    columns, heights = [], []
    for part in _batches(per_tri, _BATCH):
        owner, local = _expand(per_tri[part])
        t = owner + part.start
        ci = c0[t, 0] + local // span[t, 1]
        cj = c0[t, 1] + local % span[t, 1]
        cid = ci * ncell[1] + cj
        owner2, local2 = _expand(per_cell[cid])
        t = t[owner2]
        col = order[cell_start[cid[owner2]] + local2]
        p = xy[col]
        inside = np.ones(len(t), dtype=bool)
        z = np.zeros(len(t))
        for e, (_, _, k) in enumerate(corner):
            u, d, wo = edge_u[e][t], edge_d[e][t], edge_o[e][t]
            wp = d[:, 0] * (p[:, 1] - u[:, 1]) - d[:, 1] * (p[:, 0] - u[:, 0])
            # on the edge itself: only the triangle on the edge's positive side owns it
            inside &= np.where(wo > 0, wp >= 0, wp < 0) & (wo != 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                z += np.where(wo != 0, wp / wo, 0.0) * tri[t, k, 2]
        columns.append(col[inside])
        heights.append(z[inside])
    column = np.concatenate(columns) if columns else np.zeros(0, np.int64)
    z = np.concatenate(heights) if heights else np.zeros(0)

    # A line grazing a vertex of a fold can still be miscounted in floating
    # point; an odd count shows it. Such lines move by a negligible amount.
    odd = np.flatnonzero(np.bincount(column, minlength=len(xy)) % 2 == 1)
    if len(odd) and _retries > 0:
        shift = cell * 1e-7 * 10.0 ** (3 - _retries) * np.array([0.7548776662, 0.5698402910])
        keep_rows = ~np.isin(column, odd)
        sub_col, sub_z = vertical_crossings(tri, xy[odd] + shift, cell, _retries - 1)
        column = np.concatenate([column[keep_rows], odd[sub_col]])
        z = np.concatenate([z[keep_rows], sub_z])
    return column, z


def contains(mesh, points: np.ndarray) -> np.ndarray:
    """Which points lie inside a closed mesh.

    Args:
        mesh: watertight trimesh.Trimesh (or (T, 3, 3) triangles).
        points: (N, 3).
    Returns:
        (N,) bool. Points on the surface may go either way.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    column, z = vertical_crossings(mesh, points[:, :2])
    above = z > points[column, 2]
    return np.bincount(column[above], minlength=len(points)) % 2 == 1


def column_inside(triangles, xy: np.ndarray, z0: np.ndarray, spacing: float,
                  count: int) -> np.ndarray:
    """Which points of evenly spaced vertical columns lie inside a closed mesh.

    Column m holds the points ``(xy[m], z0[m] + k * spacing)`` for k = 0..count-1.

    Args:
        triangles: watertight trimesh.Trimesh or (T, 3, 3) triangles.
        xy: (M, 2) column positions.
        z0: (M,) height of each column's first point.
        spacing: vertical distance between points.
        count: points per column.
    Returns:
        (M, count) bool.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    z0 = np.broadcast_to(np.asarray(z0, dtype=np.float64), (len(xy),))
    cell = spacing if len(xy) > 1 else None
    column, z = vertical_crossings(triangles, xy, cell=cell)
    # point k lies below a crossing when k < first = ceil((z - z0) / spacing)
    first = np.clip(np.ceil((z - z0[column]) / spacing), 0, count).astype(np.int64)
    hist = np.bincount(column * (count + 1) + first, minlength=len(xy) * (count + 1))
    hist = hist.reshape(len(xy), count + 1).astype(np.int32)
    above = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1]
    return above[:, 1:] % 2 == 1


def lattice_inside(triangles, origin, spacing: float, shape) -> np.ndarray:
    """Which nodes of a regular lattice lie inside a closed mesh.

    Args:
        triangles: watertight trimesh.Trimesh or (T, 3, 3) triangles.
        origin: (3,) position of node [0, 0, 0].
        spacing: distance between neighbouring nodes.
        shape: (nx, ny, nz) node counts.
    Returns:
        (nx, ny, nz) bool.
    """
    origin = np.asarray(origin, dtype=np.float64)
    nx, ny, nz = (int(n) for n in shape)
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    xy = origin[:2] + spacing * np.stack([ii.ravel(), jj.ravel()], axis=1)
    inside = column_inside(triangles, xy, origin[2], spacing, nz)
    return inside.reshape(nx, ny, nz)


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                               c: np.ndarray) -> np.ndarray:
    """Closest point of each triangle to each point (Ericson, Real-Time Collision Detection 5.1.5).

    Args:
        p: (K, 3) points.
        a, b, c: (K, 3) triangle corners, triangle i belonging to point i.
    Returns:
        (K, 3) closest points.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = np.nan_to_num(d1 / (d1 - d3))
        t_ac = np.nan_to_num(d2 / (d2 - d6))
        t_bc = np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        denom = va + vb + vc
        denom = np.where(denom == 0, 1.0, denom)
        v, w = vb / denom, vc / denom
    # regions in Ericson's order: the first that holds wins
    region = np.select(
        [
            (d1 <= 0) & (d2 <= 0),
            (d3 >= 0) & (d4 <= d3),
            (vc <= 0) & (d1 >= 0) & (d3 <= 0),
            (d6 >= 0) & (d5 <= d6),
            (vb <= 0) & (d2 >= 0) & (d6 <= 0),
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
        ],
        [0, 1, 2, 3, 4, 5],
        default=6,
    )
    out = a + ab * v[:, None] + ac * w[:, None]
    for code, value in (
        (0, a),
        (1, b),
        (2, a + ab * t_ab[:, None]),
        (3, c),
        (4, a + ac * t_ac[:, None]),
        (5, b + (c - b) * t_bc[:, None]),
    ):
        sel = region == code
        out[sel] = value[sel]
    return out


def lattice_band_distance(triangles, origin, spacing: float, shape,
                          band: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact unsigned distances for the lattice nodes within ``band`` of the surface.

    Each triangle visits only the nodes of its slab (``band`` either side of its
    plane, inside its bounding box grown by ``band``), walking along the axis
    closest to its normal, so large flat triangles cost their area, not their
    bounding volume.

    Args:
        triangles: trimesh.Trimesh or (T, 3, 3) triangles.
        origin: (3,) position of node [0, 0, 0].
        spacing: node spacing.
        shape: (nx, ny, nz).
        band: distance up to which nodes get exact values.
    Returns:
        distance (nx*ny*nz,) flat in C order, exact where <= band, an upper bound
        or inf elsewhere; closest (nx*ny*nz, 3) the matching surface points (nan
        where the distance is inf).
    """
    tri = triangle_array(triangles)
    origin = np.asarray(origin, dtype=np.float64)
    dims = np.asarray(shape, dtype=np.int64)
    nx, ny, nz = (int(n) for n in dims)
    dist = np.full(nx * ny * nz, np.inf)
    closest = np.full((nx * ny * nz, 3), np.nan)
    if len(tri) == 0:
        return dist, closest

    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    ax = np.argmax(np.abs(normal), axis=1)
    bx, cx = (ax + 1) % 3, (ax + 2) % 3
    rows = np.arange(len(tri))
    tmin, tmax = tri.min(1), tri.max(1)

    def node_range(lo, hi, axis):
        i0 = np.ceil((lo - origin[axis]) / spacing)
        i1 = np.floor((hi - origin[axis]) / spacing)
        i0 = np.clip(i0, 0, dims[axis] - 1).astype(np.int64)
        i1 = np.clip(i1, -1, dims[axis] - 1).astype(np.int64)
        return i0, i1

    b0, b1 = node_range(tmin[rows, bx] - band, tmax[rows, bx] + band, bx)
    c0, c1 = node_range(tmin[rows, cx] - band, tmax[rows, cx] + band, cx)
    nb = np.maximum(b1 - b0 + 1, 0)
    nc = np.maximum(c1 - c0 + 1, 0)
    plane = np.einsum("ij,ij->i", normal, tri[:, 0])
    n_a, n_b, n_c = normal[rows, ax], normal[rows, bx], normal[rows, cx]
    half = band / np.abs(n_a)
    centre = tri.mean(axis=1)
    reach = (np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1) + band) ** 2

    for part in _batches(nb * nc, _BATCH // 4):
        owner, local = _expand((nb * nc)[part])
        t = owner + part.start
        ib = b0[t] + local // nc[t]
        ic = c0[t] + local % nc[t]
        xb = origin[bx[t]] + ib * spacing
        xc = origin[cx[t]] + ic * spacing
        xa = (plane[t] - n_b[t] * xb - n_c[t] * xc) / n_a[t]
        lo = np.maximum(xa - half[t], tmin[t, ax[t]] - band)
        hi = np.minimum(xa + half[t], tmax[t, ax[t]] + band)
        ia0 = np.clip(np.ceil((lo - origin[ax[t]]) / spacing), 0, dims[ax[t]] - 1)
        ia1 = np.clip(np.floor((hi - origin[ax[t]]) / spacing), -1, dims[ax[t]] - 1)
        count = np.maximum(ia1 - ia0 + 1, 0).astype(np.int64)
        owner2, local2 = _expand(count)
        for start in range(0, len(owner2), _BATCH):
            sub = slice(start, start + _BATCH)
            o2 = owner2[sub]
            tt = t[o2]
            index = np.empty((len(o2), 3), dtype=np.int64)
            r = np.arange(len(o2))
            index[r, ax[tt]] = ia0[o2].astype(np.int64) + local2[sub]
            index[r, bx[tt]] = ib[o2]
            index[r, cx[tt]] = ic[o2]
            node = origin + index * spacing
            # the slab's corners lie beyond the band: drop them before the exact test
            near = np.einsum("ij,ij->i", node - centre[tt], node - centre[tt]) <= reach[tt]
            node, index, tt = node[near], index[near], tt[near]
            cp = closest_point_on_triangles(node, tri[tt, 0], tri[tt, 1], tri[tt, 2])
            d = np.linalg.norm(node - cp, axis=1)
            flat = (index[:, 0] * ny + index[:, 1]) * nz + index[:, 2]
            np.minimum.at(dist, flat, d)
            best = d <= dist[flat]
            closest[flat[best]] = cp[best]
    return dist, closest


def lattice_signed_distance(triangles, origin, spacing: float, shape,
                            band: float | None = None) -> np.ndarray:
    """Signed distance from every node of a regular lattice to a closed mesh.

    Args:
        triangles: watertight trimesh.Trimesh or (T, 3, 3) triangles.
        origin: (3,) position of node [0, 0, 0].
        spacing: node spacing.
        shape: (nx, ny, nz).
        band: nodes closer than this get exact distances (default 2 spacings);
            the others the distance to the closest surface point of their
            nearest band node.
    Returns:
        (nx, ny, nz) float64, negative inside.
    """
    tri = triangle_array(triangles)
    shape = tuple(int(n) for n in shape)
    origin = np.asarray(origin, dtype=np.float64)
    band = 2.0 * spacing if band is None else max(float(band), spacing)
    inside = lattice_inside(tri, origin, spacing, shape)
    dist, closest = lattice_band_distance(tri, origin, spacing, shape, band)
    seeds = dist <= band
    if not seeds.any():
        raise ValueError("no lattice node lies near the surface: the lattice misses the mesh")
    if not seeds.all():
        # nearest band node of every other node, then its closest surface point
        nearest = ndimage.distance_transform_edt(
            ~seeds.reshape(shape), return_distances=False, return_indices=True
        )
        far = np.flatnonzero(~seeds)
        source = np.ravel_multi_index(tuple(n.ravel()[far] for n in nearest), shape)
        node = origin + np.stack(np.unravel_index(far, shape), axis=1) * spacing
        closest[far] = closest[source]
        dist[far] = np.linalg.norm(node - closest[far], axis=1)
        _sweep_closest_points(dist, closest, far, node, shape)
    values = dist.reshape(shape)
    return np.where(inside, -values, values)


def _sweep_closest_points(dist: np.ndarray, closest: np.ndarray, free: np.ndarray,
                          node: np.ndarray, shape, passes: int = 2) -> None:
    """Let free nodes adopt a face neighbour's closest point when it is nearer.

    The nearest band node can sit across a medial surface from the true closest
    feature; a neighbour usually does not. Updates ``dist`` and ``closest`` in place.

    Args:
        dist: (nx*ny*nz,) distances, flat in C order.
        closest: (nx*ny*nz, 3) closest surface points.
        free: (F,) flat indices of the nodes that may change.
        node: (F, 3) positions of those nodes.
        shape: (nx, ny, nz).
    """
    coords = np.unravel_index(free, shape)
    strides = (shape[1] * shape[2], shape[2], 1)
    for _ in range(passes):
        for axis in range(3):
            for step in (1, -1):
                ok = coords[axis] >= 1 if step == 1 else coords[axis] <= shape[axis] - 2
                target = free[ok]
                candidate = closest[target - step * strides[axis]]
                d = np.linalg.norm(node[ok] - candidate, axis=1)
                better = d < dist[target]
                dist[target[better]] = d[better]
                closest[target[better]] = candidate[better]


def unsigned_distance(mesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance from each point to the surface, and the closest surface point.

    Candidate triangles come from a k-d tree of triangle centres, pruned with
    bounding-sphere bounds, then every candidate gets the exact closest-point test.
    (``trimesh.proximity.closest_point`` can miss the closest triangle by a few
    micrometres; this does not.)

    Args:
        mesh: trimesh.Trimesh or (T, 3, 3) triangles.
        points: (N, 3).
    Returns:
        distance (N,) and closest (N, 3).
    """
    tri = triangle_array(mesh)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0 or len(tri) == 0:
        return np.full(len(points), np.inf), np.full((len(points), 3), np.nan)
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    tree = cKDTree(centre)
    k = min(8, len(tri))
    gap, nearest = tree.query(points, k=k)
    gap, nearest = gap.reshape(len(points), k), nearest.reshape(len(points), k)
    # every point of a triangle lies within its radius of its centre
    upper = np.min(gap + radius[nearest], axis=1)
    lists = tree.query_ball_point(points, upper + radius.max(), return_sorted=False)
    counts = np.fromiter((len(c) for c in lists), dtype=np.int64, count=len(points))
    candidate = np.concatenate([np.asarray(c, dtype=np.int64) for c in lists])
    owner = np.repeat(np.arange(len(points)), counts)
    offset = points[owner] - centre[candidate]
    keep = np.einsum("ij,ij->i", offset, offset) <= (upper[owner] + radius[candidate]) ** 2
    owner, candidate = owner[keep], candidate[keep]
    distance = np.full(len(points), np.inf)
    closest = np.full((len(points), 3), np.nan)
    for start in range(0, len(owner), _BATCH):
        o, t = owner[start:start + _BATCH], candidate[start:start + _BATCH]
        cp = closest_point_on_triangles(points[o], tri[t, 0], tri[t, 1], tri[t, 2])
        d = np.linalg.norm(points[o] - cp, axis=1)
        np.minimum.at(distance, o, d)
        best = d <= distance[o]
        closest[o[best]] = cp[best]
    return distance, closest


def depth(mesh, points: np.ndarray) -> np.ndarray:
    """Exact signed depth below a closed surface: positive inside, negative outside.

    (The opposite sign of a signed distance field; it is trimesh's convention.)

    Args:
        mesh: watertight trimesh.Trimesh or (T, 3, 3) triangles.
        points: (N, 3).
    Returns:
        (N,) depths in the mesh's units.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    distance, _ = unsigned_distance(mesh, points)
    return np.where(contains(mesh, points), distance, -distance)
