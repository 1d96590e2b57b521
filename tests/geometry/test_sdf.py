"""Signed distance grids against trimesh's exact signed distance."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dejaview.errors import GeometryError
from dejaview.geometry import distance
from dejaview.geometry.sdf import SignedDistanceGrid, load_or_build_sdf


def _near_surface(mesh, spacing, count=3000, seed=0):
    """(count, 3) points within a few spacings of the surface."""
    rng = np.random.default_rng(seed)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return points + rng.normal(scale=1.5 * spacing, size=points.shape)


def _exact_sdf(mesh, points):
    """Signed distance, negative inside, from trimesh (which is positive inside)."""
    return -trimesh.proximity.signed_distance(mesh, points)


@pytest.fixture(scope="module")
def table_grid(table_mesh):
    return SignedDistanceGrid.from_mesh(table_mesh, spacing=0.01, padding=0.1)


@pytest.mark.parametrize("name, spacing", [("box", 0.005), ("table", 0.01)])
def test_sign_and_accuracy_near_the_surface(request, name, spacing, table_grid):
    mesh = request.getfixturevalue(f"{name}_mesh")
    grid = (table_grid if name == "table"
            else SignedDistanceGrid.from_mesh(mesh, spacing=spacing, padding=0.03))
    points = _near_surface(mesh, spacing)
    exact = _exact_sdf(mesh, points)
    got = grid.query(points)
    clear = np.abs(exact) > 0.5 * spacing
    np.testing.assert_array_equal(np.sign(got[clear]), np.sign(exact[clear]))
    error = np.abs(got - exact)
    # flat faces interpolate exactly; sharp edges and corners cost trilinear error
    assert np.median(error) < 0.01 * spacing
    assert error.max() < 0.5 * spacing


def test_nodes_near_the_surface_are_exact(table_mesh, table_grid):
    rng = np.random.default_rng(1)
    flat = rng.choice(table_grid.values.size, 4000, replace=False)
    nodes = table_grid.origin + np.stack(np.unravel_index(flat, table_grid.shape), 1) * 0.01
    exact = -distance.depth(table_mesh, nodes)
    band = np.abs(exact) <= 0.02
    np.testing.assert_allclose(table_grid.values.ravel()[flat][band], exact[band], atol=1e-12)
    np.testing.assert_allclose(table_grid.values.ravel()[flat], exact, atol=0.003)


def test_grid_covers_mesh_with_padding(table_mesh, table_grid):
    lo, hi = table_grid.bounds
    assert np.all(lo <= table_mesh.bounds[0] - 0.1 + 1e-9)
    assert np.all(hi >= table_mesh.bounds[1] + 0.1 - 1e-9)
    assert table_grid.values.dtype == np.float64
    assert table_grid.values.shape == table_grid.shape


def test_query_at_nodes_returns_node_values(table_grid):
    index = np.array([[3, 4, 5], [70, 50, 80], [140, 100, 95]])
    points = table_grid.origin + index * table_grid.spacing
    np.testing.assert_allclose(table_grid.query(points),
                               table_grid.values[tuple(index.T)], atol=1e-12)


def test_query_outside_the_grid_is_conservative(table_grid):
    lo, hi = table_grid.bounds
    inside_box = np.array([[0.0, 0.0, hi[2]]])
    above = inside_box + [0.0, 0.0, 0.5]
    np.testing.assert_allclose(table_grid.query(above), table_grid.query(inside_box) + 0.5)
    far = np.array([[10.0, -10.0, 5.0], [lo[0] - 1.0, 0.0, 0.3]])
    exact = np.linalg.norm(far - [[0.6, -0.4, 0.75], [-0.6, 0.0, 0.3]], axis=1)
    assert np.all(table_grid.query(far) > 0)
    assert np.all(table_grid.query(far) >= exact - 0.02)


def test_query_keeps_leading_dimensions(table_grid):
    points = np.zeros((2, 5, 3))
    assert table_grid.query(points).shape == (2, 5)


def test_save_load_round_trip(tmp_path, table_grid):
    path = tmp_path / "grid.npz"
    table_grid.save(path)
    back = SignedDistanceGrid.load(path)
    np.testing.assert_array_equal(back.values, table_grid.values)
    np.testing.assert_array_equal(back.origin, table_grid.origin)
    assert back.spacing == table_grid.spacing


def test_load_errors(tmp_path):
    with pytest.raises(GeometryError, match="missing.npz"):
        SignedDistanceGrid.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(GeometryError, match="bad.npz: not a signed distance grid"):
        SignedDistanceGrid.load(bad)


def test_cache_is_used(tmp_path, box_mesh, monkeypatch):
    calls = []
    original = distance.lattice_signed_distance

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(distance, "lattice_signed_distance", counting)
    first = SignedDistanceGrid.from_mesh(box_mesh, spacing=0.01, padding=0.02, cache_dir=tmp_path)
    second = SignedDistanceGrid.from_mesh(box_mesh, spacing=0.01, padding=0.02, cache_dir=tmp_path)
    assert len(calls) == 1
    np.testing.assert_array_equal(first.values, second.values)
    SignedDistanceGrid.from_mesh(box_mesh, spacing=0.02, padding=0.02, cache_dir=tmp_path)
    assert len(calls) == 2

    mesh_path = tmp_path / "box.obj"
    box_mesh.export(mesh_path)
    monkeypatch.delenv("DEJAVIEW_CACHE_DIR", raising=False)
    load_or_build_sdf(mesh_path, spacing=0.01, padding=0.02)
    load_or_build_sdf(mesh_path, spacing=0.01, padding=0.02)
    assert len(calls) == 3
    assert len(list((tmp_path / ".dejaview-cache").glob("box-sdf-*.npz"))) == 1


def test_bad_parameters(box_mesh):
    with pytest.raises(GeometryError, match="spacing"):
        SignedDistanceGrid.from_mesh(box_mesh, spacing=0.0)
    with pytest.raises(GeometryError, match="padding"):
        SignedDistanceGrid.from_mesh(box_mesh, padding=-1.0)
    with pytest.raises(GeometryError, match="limit"):
        SignedDistanceGrid.from_mesh(box_mesh, spacing=1e-5)
