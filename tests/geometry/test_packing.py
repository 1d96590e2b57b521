"""Sphere packings: the file format, packing quality, determinism and the cache."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dejaview.errors import GeometryError
from dejaview.geometry import packing as packing_module
from dejaview.geometry.mesh import file_hash
from dejaview.geometry.packing import SpherePacking, load_or_build_packing


@pytest.fixture(scope="module")
def box_packing(box_mesh):
    return SpherePacking.from_mesh(box_mesh, max_spheres=256)


@pytest.fixture(scope="module")
def ball_packing(ball_mesh):
    return SpherePacking.from_mesh(ball_mesh, max_spheres=256)


def _exact_overreach(packing, mesh):
    """max(r - depth(center)) from trimesh's own signed distance (positive inside)."""
    return float(np.max(packing.radii - trimesh.proximity.signed_distance(mesh, packing.centers)))


# ------------------------------------------------------------------ quality
@pytest.mark.parametrize("name", ["box", "ball"])
def test_packing_covers_80_percent_within_2_mm(name, request):
    mesh = request.getfixturevalue(f"{name}_mesh")
    packing = request.getfixturevalue(f"{name}_packing")
    quality = packing.quality(mesh)
    assert 1 <= len(packing) <= 256
    assert quality.count == len(packing)
    assert quality.coverage >= 0.8
    assert quality.max_outside <= 0.001 + 1e-9
    assert _exact_overreach(packing, mesh) <= 0.002
    assert packing.centers.dtype == np.float64 and packing.centers.shape == (len(packing), 3)
    assert packing.radii.dtype == np.float64 and packing.radii.shape == (len(packing),)


def test_quality_coverage_of_one_inscribed_sphere(box_mesh):
    """One sphere of radius 5 cm in the 20 x 15 x 10 cm box: coverage is a volume ratio."""
    single = SpherePacking(np.zeros((1, 3)), [0.05])
    quality = single.quality(box_mesh, samples=100_000)
    assert quality.coverage == pytest.approx(4 / 3 * np.pi * 0.05**3 / 0.003, abs=0.005)
    assert quality.max_outside == pytest.approx(0.0, abs=1e-12)
    assert quality.volume == pytest.approx(0.003)


def test_quality_gap_is_the_farthest_surface_point(box_mesh, box_packing):
    """One 5 cm sphere at the 20 x 15 x 10 cm box's centre: the corners are the farthest
    surface points, |(0.1, 0.075, 0.05)| - 0.05 from the sphere; a good packing comes closer."""
    single = SpherePacking(np.zeros((1, 3)), [0.05])
    quality = single.quality(box_mesh, samples=10_000)
    assert quality.max_gap == pytest.approx(np.linalg.norm([0.1, 0.075, 0.05]) - 0.05, abs=1e-12)
    assert quality.max_deviation == quality.max_gap
    good = box_packing.quality(box_mesh, samples=10_000)
    assert 0.0 < good.max_gap < quality.max_gap
    assert good.max_deviation == max(good.max_gap, good.max_outside)


def test_zero_tolerance_keeps_every_sphere_inside(box_mesh):
    packing = SpherePacking.from_mesh(box_mesh, max_spheres=32, tolerance=0.0, resolution=0.006)
    assert _exact_overreach(packing, box_mesh) <= 1e-9


def test_packing_is_deterministic(ball_mesh):
    first = SpherePacking.from_mesh(ball_mesh, max_spheres=40, resolution=0.006)
    second = SpherePacking.from_mesh(ball_mesh, max_spheres=40, resolution=0.006)
    np.testing.assert_array_equal(first.centers, second.centers)
    np.testing.assert_array_equal(first.radii, second.radii)


def test_coverage_target_and_min_radius_stop_early(box_mesh):
    early = SpherePacking.from_mesh(box_mesh, max_spheres=256, coverage=0.5, resolution=0.006)
    assert 1 <= len(early) < 20
    coarse = SpherePacking.from_mesh(box_mesh, max_spheres=256, min_radius=0.03,
                                     resolution=0.006)
    assert np.all(coarse.radii >= 0.03)
    assert len(coarse) < 256


def test_min_radius_larger_than_anything_that_fits(box_mesh):
    with pytest.raises(GeometryError, match="no sphere fits with a radius of at least 0.2 m"):
        SpherePacking.from_mesh(box_mesh, min_radius=0.2, resolution=0.01)


def test_progress_reports_each_sphere(box_mesh):
    calls = []
    packing = SpherePacking.from_mesh(box_mesh, max_spheres=12, resolution=0.008,
                                      progress=lambda done, total: calls.append((done, total)))
    assert calls == [(i, 12) for i in range(1, len(packing) + 1)]


def test_header_records_the_parameters(box_packing):
    assert box_packing.header["max_spheres"] == "256"
    assert box_packing.header["tolerance"] == "0.001"
    assert box_packing.header["spheres"] == str(len(box_packing))


def test_non_watertight_mesh_is_refused():
    tube = trimesh.creation.cylinder(radius=0.05, height=0.1, sections=32)
    tube = trimesh.Trimesh(tube.vertices, tube.faces[np.abs(tube.face_normals[:, 2]) < 0.5])
    with pytest.raises(GeometryError, match="not watertight"):
        SpherePacking.from_mesh(tube)


@pytest.mark.parametrize("kwargs, message", [
    ({"max_spheres": 0}, "max_spheres"),
    ({"tolerance": 0.003}, "tolerance"),
    ({"coverage": 1.5}, "coverage"),
    ({"min_radius": -1.0}, "min_radius"),
    ({"resolution": 0.0}, "resolution"),
])
def test_bad_parameters(box_mesh, kwargs, message):
    with pytest.raises(GeometryError, match=message):
        SpherePacking.from_mesh(box_mesh, **kwargs)


def test_from_primitive():
    ball = SpherePacking.from_primitive("sphere", radius=0.05)
    assert len(ball) == 1 and ball.radii[0] == 0.05
    cylinder = SpherePacking.from_primitive("cylinder", radius=0.03, height=0.1, max_spheres=32,
                                              resolution=0.004)
    assert 1 <= len(cylinder) <= 32
    assert np.all(np.abs(cylinder.centers[:, 2]) <= 0.05)


def test_bounding_sphere_encloses_everything():
    pair = SpherePacking([[-1.0, 0, 0], [1.0, 0, 0]], [1.0, 1.0])
    center, radius = pair.bounding_sphere()
    np.testing.assert_allclose(center, 0.0, atol=1e-9)
    assert radius == pytest.approx(2.0)
    rng = np.random.default_rng(0)
    cloud = SpherePacking(rng.normal(size=(50, 3)), rng.uniform(0.1, 0.5, 50))
    center, radius = cloud.bounding_sphere()
    reach = np.linalg.norm(cloud.centers - center, axis=1) + cloud.radii
    assert np.all(reach <= radius + 1e-12)
    assert radius <= 1.02 * reach.max()


# -------------------------------------------------------------- file format
def test_write_read_round_trip(tmp_path, box_mesh):
    mesh_path = tmp_path / "meshes" / "box.obj"
    mesh_path.parent.mkdir()
    box_mesh.export(mesh_path)
    rng = np.random.default_rng(5)
    packing = SpherePacking(rng.normal(size=(20, 3)), rng.uniform(1e-4, 0.1, 20),
                            {"note": "hello world"})
    out = tmp_path / "packings" / "box.spheres"
    out.parent.mkdir()
    packing.write(out, source=mesh_path)
    back = SpherePacking.read(out)
    np.testing.assert_array_equal(back.centers, packing.centers)
    np.testing.assert_array_equal(back.radii, packing.radii)
    assert back.header["source"] == "../meshes/box.obj"
    assert back.header["sha256"] == file_hash(mesh_path)
    assert back.header["note"] == "hello world"
    assert len(back) == 20
    assert out.read_text().startswith("#")


def test_read_accepts_comments_and_blank_lines(tmp_path):
    path = tmp_path / "a.spheres"
    path.write_text("# made by hand\n\n  # indented comment\n0 0 0 0.5\n1e-3 -2 3.5 1\n")
    packing = SpherePacking.read(path)
    np.testing.assert_array_equal(packing.radii, [0.5, 1.0])


@pytest.mark.parametrize("line, reason", [
    ("0 0 0", "expected 4 numbers"),
    ("0 0 0 1 2", "expected 4 numbers"),
    ("0 0 x 1", "not a number: 'x'"),
    ("0 nan 0 1", "non-finite"),
    ("0 0 inf 1", "non-finite"),
    ("0 0 0 0", "radius must be positive"),
    ("0 0 0 -0.1", "radius must be positive"),
])
def test_read_errors_name_file_and_line(tmp_path, line, reason):
    path = tmp_path / "bad.spheres"
    path.write_text(f"# header\n0 0 0 0.1\n{line}\n")
    with pytest.raises(GeometryError) as caught:
        SpherePacking.read(path)
    assert f"{path}:3: " in str(caught.value)
    assert reason in str(caught.value)


def test_read_empty_and_missing(tmp_path):
    empty = tmp_path / "empty.spheres"
    empty.write_text("# only a comment\n\n")
    with pytest.raises(GeometryError, match=r"empty\.spheres: the file holds no spheres"):
        SpherePacking.read(empty)
    with pytest.raises(GeometryError, match=r"missing\.spheres: sphere packing file not found"):
        SpherePacking.read(tmp_path / "missing.spheres")


def test_constructor_rejects_bad_arrays():
    with pytest.raises(GeometryError):
        SpherePacking(np.zeros((2, 3)), [1.0])
    with pytest.raises(GeometryError):
        SpherePacking(np.zeros((1, 3)), [0.0])


# -------------------------------------------------------------------- cache
@pytest.fixture
def counted_builds(monkeypatch):
    """Counts SpherePacking.from_mesh calls."""
    calls = []
    original = SpherePacking.from_mesh.__func__

    def counting(cls, *args, **kwargs):
        calls.append(kwargs)
        return original(cls, *args, **kwargs)

    monkeypatch.setattr(SpherePacking, "from_mesh", classmethod(counting))
    return calls


def test_cache_hit_does_not_rebuild(tmp_path, box_mesh, counted_builds, monkeypatch):
    monkeypatch.delenv("DEJAVIEW_CACHE_DIR", raising=False)
    mesh_path = tmp_path / "box.obj"
    box_mesh.export(mesh_path)
    first = load_or_build_packing(mesh_path, max_spheres=16, resolution=0.008)
    cached = list((tmp_path / ".dejaview-cache").glob("box-*.spheres"))
    assert len(cached) == 1
    stamp = cached[0].stat().st_mtime_ns
    second = load_or_build_packing(mesh_path, max_spheres=16, resolution=0.008)
    assert len(counted_builds) == 1
    assert cached[0].stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(first.centers, second.centers)
    np.testing.assert_array_equal(first.radii, second.radii)
    assert SpherePacking.read(cached[0]).header["sha256"] == file_hash(mesh_path)
    # other parameters, or another mesh under the same name, are other entries
    load_or_build_packing(mesh_path, max_spheres=17, resolution=0.008)
    assert len(counted_builds) == 2
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(mesh_path)
    load_or_build_packing(mesh_path, max_spheres=16, resolution=0.008)
    assert len(counted_builds) == 3


def test_cache_dir_from_environment(tmp_path, box_mesh, counted_builds, monkeypatch):
    monkeypatch.setenv("DEJAVIEW_CACHE_DIR", str(tmp_path / "elsewhere"))
    mesh_path = tmp_path / "box.obj"
    box_mesh.export(mesh_path)
    load_or_build_packing(mesh_path, max_spheres=8, resolution=0.008)
    assert len(list((tmp_path / "elsewhere").glob("box-*.spheres"))) == 1
    assert not (tmp_path / ".dejaview-cache").exists()


def test_explicit_spheres_file_wins(tmp_path, box_mesh, counted_builds):
    mesh_path = tmp_path / "box.obj"
    box_mesh.export(mesh_path)
    given = tmp_path / "given.spheres"
    SpherePacking([[0, 0, 0]], [0.05]).write(given)
    packing = load_or_build_packing(mesh_path, spheres_path=given, cache_dir=tmp_path / "c")
    assert len(packing) == 1 and counted_builds == []
    # a named file that does not exist yet: build (and cache) instead
    packing = load_or_build_packing(mesh_path, spheres_path=tmp_path / "absent.spheres",
                                    max_spheres=8, resolution=0.008,
                                    cache_dir=tmp_path / "c")
    assert len(counted_builds) == 1 and len(packing) == 8


def test_explicit_spheres_file_of_another_mesh_warns(tmp_path, box_mesh):
    mesh_path = tmp_path / "box.obj"
    box_mesh.export(mesh_path)
    given = tmp_path / "given.spheres"
    SpherePacking([[0, 0, 0]], [0.05]).write(given, source=mesh_path)
    load_or_build_packing(mesh_path, spheres_path=given)  # same mesh: no warning
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(mesh_path)
    with pytest.warns(UserWarning, match="another version"):
        load_or_build_packing(mesh_path, spheres_path=given)
    given.write_text("# sha256: placeholder (hand-written)\n0 0 0 0.05\n")
    load_or_build_packing(mesh_path, spheres_path=given)  # not a digest: no warning


def test_unknown_parameter_is_an_error(tmp_path, box_mesh):
    mesh_path = tmp_path / "box.obj"
    box_mesh.export(mesh_path)
    with pytest.raises(TypeError):
        load_or_build_packing(mesh_path, radius=3)


def test_algorithm_name_is_part_of_the_header(box_packing):
    assert packing_module.ALGORITHM in box_packing.header["generator"]
