"""Mesh loading, repair, primitives and mass properties."""

from __future__ import annotations

import hashlib
import json
import socket
import struct

import numpy as np
import pytest
import trimesh

from dejaview.errors import GeometryError
from dejaview.geometry.mesh import (
    cache_folder,
    file_hash,
    load_mesh,
    mass_properties,
    primitive_mass_properties,
    primitive_mesh,
    watertight_mesh,
)


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".glb"])
def test_load_each_format(tmp_path, box_mesh, suffix):
    path = tmp_path / f"box{suffix}"
    box_mesh.export(path)
    mesh = load_mesh(path)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(0.2 * 0.15 * 0.1, rel=1e-6)
    np.testing.assert_allclose(mesh.bounds, box_mesh.bounds, atol=1e-6)
    assert mesh.metadata["file_name"] == path.name


def test_uppercase_suffix_is_accepted(tmp_path, box_mesh):
    path = tmp_path / "BOX.STL"
    box_mesh.export(path, file_type="stl")
    assert load_mesh(path).is_watertight


def test_glb_scene_is_flattened_with_its_transforms(tmp_path):
    scene = trimesh.Scene()
    cube = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    scene.add_geometry(cube, node_name="a", transform=trimesh.transformations.translation_matrix((1, 0, 0)))
    scene.add_geometry(cube, node_name="b", transform=trimesh.transformations.translation_matrix((0, 0, 2)))
    path = tmp_path / "two.glb"
    scene.export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 24
    np.testing.assert_allclose(mesh.bounds, [[-0.05, -0.05, -0.05], [1.05, 0.05, 2.05]], atol=1e-6)


def _glb_with_remote_buffer(uri: str) -> bytes:
    """A GLB whose only buffer lives at ``uri`` (no binary chunk)."""
    gltf = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"uri": uri, "byteLength": 42}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"},
        ],
    }
    body = json.dumps(gltf).encode()
    body += b" " * (-len(body) % 4)
    chunk = struct.pack("<II", len(body), 0x4E4F534A) + body
    return struct.pack("<III", 0x46546C67, 2, 12 + len(chunk)) + chunk


def test_glb_never_fetches_remote_references(tmp_path, monkeypatch):
    calls = []

    def refuse(self, address):
        calls.append(address)
        raise OSError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    path = tmp_path / "remote.glb"
    path.write_bytes(_glb_with_remote_buffer("http://127.0.0.1:9/mesh.bin"))
    with pytest.raises(GeometryError, match="remote.glb"):
        load_mesh(path)
    assert calls == []


def test_glb_cannot_reach_files_outside_its_folder(tmp_path):
    (tmp_path / "outside.bin").write_bytes(bytes(42))
    folder = tmp_path / "meshes"
    folder.mkdir()
    path = folder / "escape.glb"
    path.write_bytes(_glb_with_remote_buffer("../outside.bin"))
    with pytest.raises(GeometryError, match="escape.glb"):
        load_mesh(path)


def test_missing_file_names_the_path(tmp_path):
    with pytest.raises(GeometryError, match=r"nothere\.obj: mesh file not found"):
        load_mesh(tmp_path / "nothere.obj")


def test_unsupported_suffix(tmp_path):
    path = tmp_path / "mesh.fbx"
    path.write_text("whatever")
    with pytest.raises(GeometryError, match=r"mesh\.fbx: unsupported mesh format '\.fbx'"):
        load_mesh(path)


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".glb"])
def test_garbage_content(tmp_path, suffix):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(bytes(np.random.default_rng(1).integers(0, 256, 300, dtype=np.uint8)))
    with pytest.raises(GeometryError, match=f"garbage\\{suffix}"):
        load_mesh(path)


def test_file_without_triangles(tmp_path):
    path = tmp_path / "empty.obj"
    path.write_text("# nothing here\nv 0 0 0\nv 1 0 0\n")
    with pytest.raises(GeometryError, match=r"empty\.obj: .*no triangles"):
        load_mesh(path)


def test_file_hash_is_sha256_of_the_bytes(tmp_path):
    path = tmp_path / "data.bin"
    path.write_bytes(b"dejaview" * 1000)
    assert file_hash(path) == hashlib.sha256(b"dejaview" * 1000).hexdigest()
    with pytest.raises(GeometryError, match="missing.bin"):
        file_hash(tmp_path / "missing.bin")


def test_cache_folder_default_and_override(tmp_path, monkeypatch):
    monkeypatch.delenv("DEJAVIEW_CACHE_DIR", raising=False)
    assert cache_folder(tmp_path / "m.obj") == tmp_path / ".dejaview-cache"
    monkeypatch.setenv("DEJAVIEW_CACHE_DIR", str(tmp_path / "env"))
    assert cache_folder(tmp_path / "m.obj") == tmp_path / "env"
    assert cache_folder(tmp_path / "m.obj", tmp_path / "given") == tmp_path / "given"


# ---------------------------------------------------------------- primitives
def test_primitives_are_centred_watertight_and_sized():
    box = primitive_mesh("box", size=(0.2, 0.1, 0.3))
    np.testing.assert_allclose(box.bounds, [[-0.1, -0.05, -0.15], [0.1, 0.05, 0.15]])
    ball = primitive_mesh("sphere", radius=0.05)
    cyl = primitive_mesh("cylinder", radius=0.03, height=0.2)
    np.testing.assert_allclose(cyl.bounds[:, 2], [-0.1, 0.1])
    for mesh in (box, ball, cyl):
        assert mesh.is_watertight and mesh.volume > 0
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)


@pytest.mark.parametrize("shape, kwargs", [
    ("cone", {"radius": 1.0}),
    ("box", {}),
    ("box", {"size": (1, -1, 1)}),
    ("sphere", {"radius": 0.0}),
    ("cylinder", {"radius": 1.0}),
])
def test_bad_primitives(shape, kwargs):
    with pytest.raises(GeometryError, match=shape):
        primitive_mesh(shape, **kwargs)


# ---------------------------------------------------------- mass properties
@pytest.mark.parametrize("shape, kwargs", [
    ("box", {"size": (0.2, 0.15, 0.1)}),
    ("sphere", {"radius": 0.05}),
    ("cylinder", {"radius": 0.04, "height": 0.1}),
])
def test_mesh_mass_properties_match_closed_forms(shape, kwargs):
    exact = primitive_mass_properties(shape, **kwargs, density=800.0)
    props = mass_properties(primitive_mesh(shape, **kwargs), density=800.0)
    assert props.mass == pytest.approx(exact.mass, rel=0.01)
    np.testing.assert_allclose(props.center_of_mass, 0.0, atol=1e-9)
    np.testing.assert_allclose(np.diag(props.inertia), np.diag(exact.inertia), rtol=0.01)
    off_diagonal = props.inertia - np.diag(np.diag(props.inertia))
    assert np.abs(off_diagonal).max() < 1e-3 * np.abs(exact.inertia).max()


def test_closed_forms():
    box = primitive_mass_properties("box", size=(1.0, 2.0, 3.0), density=1.0)
    assert box.mass == pytest.approx(6.0)
    np.testing.assert_allclose(np.diag(box.inertia), [6 * 13 / 12, 6 * 10 / 12, 6 * 5 / 12])
    ball = primitive_mass_properties("sphere", radius=2.0, mass=3.0)
    np.testing.assert_allclose(np.diag(ball.inertia), 0.4 * 3.0 * 4.0)
    cyl = primitive_mass_properties("cylinder", radius=1.0, height=2.0, mass=6.0)
    np.testing.assert_allclose(np.diag(cyl.inertia), [6 * 7 / 12, 6 * 7 / 12, 3.0])


def test_given_mass_rescales_density(box_mesh):
    props = mass_properties(box_mesh, mass=0.5)
    reference = mass_properties(box_mesh, density=1000.0)
    assert props.mass == pytest.approx(0.5)
    np.testing.assert_allclose(props.inertia, reference.inertia * 0.5 / reference.mass)


def test_inertia_is_about_the_centre_of_mass(box_mesh):
    moved = box_mesh.copy()
    moved.apply_translation((1.0, 2.0, 3.0))
    props = mass_properties(moved)
    np.testing.assert_allclose(props.center_of_mass, (1.0, 2.0, 3.0), atol=1e-12)
    np.testing.assert_allclose(props.inertia, mass_properties(box_mesh).inertia, rtol=1e-9,
                               atol=1e-12)


def test_inverted_mesh_is_fixed(box_mesh):
    inverted = box_mesh.copy()
    inverted.invert()
    assert inverted.volume < 0
    assert mass_properties(inverted).mass == pytest.approx(3.0)


def test_small_hole_is_repaired(box_mesh):
    holed = trimesh.Trimesh(box_mesh.vertices, box_mesh.faces[1:], process=False)
    assert not holed.is_watertight
    assert watertight_mesh(holed).is_watertight
    assert mass_properties(holed).mass == pytest.approx(3.0)


def test_open_tube_cannot_be_repaired():
    tube = trimesh.creation.cylinder(radius=0.05, height=0.1, sections=32)
    sides = np.abs(tube.face_normals[:, 2]) < 0.5  # drop both caps
    tube = trimesh.Trimesh(tube.vertices, tube.faces[sides], metadata={"file_path": "tube.obj"})
    with pytest.raises(GeometryError, match=r"tube\.obj: the mesh is not watertight"):
        mass_properties(tube)


def test_bad_mass_and_density(box_mesh):
    with pytest.raises(GeometryError, match="mass must be a positive"):
        mass_properties(box_mesh, mass=-1.0)
    with pytest.raises(GeometryError, match="density must be a positive"):
        primitive_mass_properties("sphere", radius=1.0, density=0.0)
