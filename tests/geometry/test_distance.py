"""Inside tests and exact distances, checked against trimesh and brute force."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dejaview.geometry import distance


def _annulus():
    return trimesh.creation.annulus(r_min=0.03, r_max=0.04, height=0.1, sections=48)


@pytest.mark.parametrize("make", [
    lambda: trimesh.creation.box(extents=(0.2, 0.15, 0.1)),
    lambda: trimesh.creation.icosphere(subdivisions=3, radius=0.05),
    _annulus,
])
def test_contains_matches_trimesh(make):
    mesh = make()
    rng = np.random.default_rng(0)
    points = rng.uniform(mesh.bounds[0] - 0.01, mesh.bounds[1] + 0.01, (4000, 3))
    np.testing.assert_array_equal(distance.contains(mesh, points), mesh.contains(points))


def test_lattice_through_edges_and_vertices_counts_each_crossing_once():
    """Columns that run exactly through shared edges and vertices of a tessellated
    box must cross it exactly twice (all coordinates are exact binary fractions)."""
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0)).subdivide().subdivide()
    spacing = 0.25  # columns on vertices (x, y in 0.5 Z) and on edges and diagonals
    origin = np.array([-1.5, -1.5, -1.375])
    shape = (13, 13, 12)
    inside = distance.lattice_inside(box, origin, spacing, shape)
    nodes = origin + np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1) * spacing
    expected = np.all(np.abs(nodes) < 1.0, axis=-1)
    off_walls = np.all(np.abs(nodes[..., :2]) != 1.0, axis=-1)  # nodes in a wall may go either way
    assert off_walls.sum() > 1000
    np.testing.assert_array_equal(inside[off_walls], expected[off_walls])


def test_shifted_box_with_columns_on_its_faces():
    """Columns lying in a vertical face of the box hit only vertical triangles."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    points = np.array([[0.1, 0.0, 0.0], [0.0, 0.05, 0.0], [0.1, 0.1, 0.05], [0.3, 0.0, 0.0]])
    inside = distance.contains(box, points)
    assert inside[1] and not inside[3]


def test_closest_point_on_triangles_covers_every_region():
    a, b, c = np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
    queries = {
        (-1, -1, 1): a, (2, -0.5, 0): b, (-0.5, 2, 0): c,  # vertex regions
        (0.5, -1, 0.3): (0.5, 0, 0), (-1, 0.5, 0): (0, 0.5, 0), (1, 1, 2): (0.5, 0.5, 0),
        (0.2, 0.3, -4): (0.2, 0.3, 0),  # face region
    }
    p = np.array(list(queries), dtype=float)
    expected = np.array([np.asarray(v, dtype=float) for v in queries.values()])
    n = len(p)
    got = distance.closest_point_on_triangles(p, np.tile(a, (n, 1)), np.tile(b, (n, 1)),
                                              np.tile(c, (n, 1)))
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_unsigned_distance_matches_brute_force():
    rng = np.random.default_rng(3)
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    mesh.vertices *= rng.uniform(0.8, 1.2, (len(mesh.vertices), 1))
    points = rng.uniform(-0.08, 0.08, (300, 3))
    got, closest = distance.unsigned_distance(mesh, points)
    tri = mesh.triangles
    for point, d, cp in zip(points, got, closest):
        all_cp = distance.closest_point_on_triangles(
            np.tile(point, (len(tri), 1)), tri[:, 0], tri[:, 1], tri[:, 2])
        assert d == pytest.approx(np.linalg.norm(all_cp - point, axis=1).min(), abs=1e-15)
        assert np.linalg.norm(cp - point) == pytest.approx(d, abs=1e-15)


def test_depth_is_positive_inside(box_mesh):
    depth = distance.depth(box_mesh, [[0, 0, 0], [0.0, 0.0, 0.06], [0.09, 0.0, 0.0]])
    np.testing.assert_allclose(depth, [0.05, -0.01, 0.01], atol=1e-12)


def test_lattice_signed_distance_matches_exact_values(table_mesh):
    spacing = 0.02
    origin = table_mesh.bounds[0] - 0.05
    shape = tuple(np.ceil((table_mesh.extents + 0.1) / spacing).astype(int) + 1)
    values = distance.lattice_signed_distance(table_mesh, origin, spacing, shape)
    rng = np.random.default_rng(0)
    flat = rng.choice(values.size, 3000, replace=False)
    nodes = origin + np.stack(np.unravel_index(flat, shape), axis=1) * spacing
    exact = -distance.depth(table_mesh, nodes)
    got = values.ravel()[flat]
    band = np.abs(exact) <= 2 * spacing
    np.testing.assert_allclose(got[band], exact[band], atol=1e-12)
    # further out: never below the true distance, and close to it
    assert np.all(np.abs(got[~band]) >= np.abs(exact[~band]) - 1e-12)
    assert np.abs(got - exact).max() <= 0.25 * spacing
    assert np.all(np.sign(got[np.abs(exact) > 1e-9]) == np.sign(exact[np.abs(exact) > 1e-9]))
