"""Build the example meshes and their sphere packings.

    python examples/build_meshes.py            # meshes and packings
    python examples/build_meshes.py --meshes   # meshes only

Writes watertight .obj files in metres to ``examples/meshes/`` and sphere
packings of the movable objects to ``examples/packings/``. Origins:

* movable objects (mug, box, ball): the centre of the bounding box;
* furniture (table, counter, shelf): the centre of the floor contact, so a pose
  with z = 0 stands it on the floor;
* floor: the centre of its top surface.

``test_mesh()`` makes the 10 000-triangle mesh of the packing benchmark on the
fly (it is not written to disk).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
MESH_DIR = HERE / "meshes"
PACKING_DIR = HERE / "packings"

# Packing budgets: the mug's is the simulator benchmark's reference.
PACKINGS = {"mug": 150, "box": 128, "ball": 64}


def _box(extents, centre) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(centre)
    return mesh


def _union(parts) -> trimesh.Trimesh:
    return trimesh.boolean.union(parts, engine="manifold")


def mug() -> trimesh.Trimesh:
    """A mug: 8 cm across, 10 cm tall, 1.2 cm wall and bottom, a ring handle on +x.

    The wall is thick for a mug so that 256 spheres reaching at most 1 mm outside
    cover over 80 % of it (a 1 cm wall tops out near 78 %).
    """
    radius, height, wall, bottom = 0.04, 0.10, 0.012, 0.012
    body = trimesh.creation.cylinder(radius=radius, height=height, sections=96)
    cavity = trimesh.creation.cylinder(radius=radius - wall, height=height, sections=96)
    cavity.apply_translation((0.0, 0.0, bottom))
    # ring in the x-z plane: 12 mm thick, reaching 2.6 cm beyond the wall
    handle = trimesh.creation.torus(major_radius=0.024, minor_radius=0.006,
                                    major_sections=64, minor_sections=24)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    handle.apply_translation((radius - 0.002, 0.0, 0.002))
    mesh = trimesh.boolean.difference([_union([body, handle]), cavity], engine="manifold")
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def box() -> trimesh.Trimesh:
    """A 20 x 15 x 10 cm box."""
    return trimesh.creation.box(extents=(0.20, 0.15, 0.10))


def ball() -> trimesh.Trimesh:
    """A ball of radius 5 cm (icosphere, 1280 faces)."""
    return trimesh.creation.icosphere(subdivisions=3, radius=0.05)


def table() -> trimesh.Trimesh:
    """A 1.2 x 0.8 m table, 0.75 m high: a 4 cm top on four 5 x 5 cm legs."""
    top = _box((1.2, 0.8, 0.04), (0.0, 0.0, 0.73))
    legs = [_box((0.05, 0.05, 0.71), (sx * 0.55, sy * 0.35, 0.355))
            for sx in (-1, 1) for sy in (-1, 1)]
    return _union([top, *legs])


def counter() -> trimesh.Trimesh:
    """A kitchen counter block, 1.0 x 0.6 x 0.9 m."""
    return _box((1.0, 0.6, 0.9), (0.0, 0.0, 0.45))


def shelf() -> trimesh.Trimesh:
    """A corner shelf: a 1.0 x 0.3 m board with its top at 1.0 m, a back panel and a
    side panel at +x, both 1.2 m high, so a box can slide along the board into the corner."""
    back = _box((1.0, 0.02, 1.2), (0.0, 0.14, 0.6))
    side = _box((0.02, 0.3, 1.2), (0.49, 0.0, 0.6))
    board = _box((0.98, 0.28, 0.02), (-0.01, -0.01, 0.99))
    return _union([back, side, board])


def floor() -> trimesh.Trimesh:
    """A 4 x 4 m slab, 2 cm thick, its top at z = 0."""
    return _box((4.0, 4.0, 0.02), (0.0, 0.0, -0.01))


def test_mesh(faces: int = 10_000, seed: int = 0) -> trimesh.Trimesh:
    """A lumpy, potato-like closed mesh with about ``faces`` triangles (benchmark input).

    A UV sphere of radius 6 cm whose radius is modulated by a few random smooth
    waves; star-shaped, so it stays watertight.

    Args:
        faces: approximate triangle count.
        seed: random seed of the waves.
    Returns:
        The mesh, centred near the origin.
    """
    rng = np.random.default_rng(seed)
    # trimesh's UV sphere with count (n, n) has about 4 n^2 faces: take the
    # first n that reaches ``faces``
    n = max(int(np.sqrt(faces / 4.0)), 4)
    sphere = trimesh.creation.uv_sphere(radius=1.0, count=(n, n))
    while len(sphere.faces) < faces:
        n += 1
        sphere = trimesh.creation.uv_sphere(radius=1.0, count=(n, n))
    direction = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    scale = np.ones(len(direction))
    for _ in range(5):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        frequency, phase = rng.uniform(1.5, 4.0), rng.uniform(0, 2 * np.pi)
        scale += 0.06 * np.sin(frequency * direction @ axis * np.pi + phase)
    mesh = trimesh.Trimesh(direction * (0.06 * scale)[:, None], sphere.faces, process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


MESHES = {
    "mug": mug,
    "box": box,
    "ball": ball,
    "table": table,
    "counter": counter,
    "shelf": shelf,
    "floor": floor,
}


def build_meshes(out: Path = MESH_DIR) -> dict[str, Path]:
    """Write every example mesh as .obj; returns name -> path."""
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, make in MESHES.items():
        mesh = make()
        if not (mesh.is_watertight and mesh.volume > 0):
            raise RuntimeError(f"{name}: the built mesh is not a closed solid")
        path = out / f"{name}.obj"
        mesh.export(path, file_type="obj", include_normals=False, include_texture=False,
                    digits=6)
        written[name] = path
        print(f"{path.relative_to(HERE.parent)}: {len(mesh.faces)} faces, "
              f"extents {np.round(mesh.extents, 3).tolist()} m, volume {mesh.volume:.4g} m^3")
    return written


def build_packings(meshes: Path = MESH_DIR, out: Path = PACKING_DIR) -> None:
    """Pack the movable example meshes into .spheres files."""
    from dejaview.geometry.mesh import load_mesh
    from dejaview.geometry.packing import SpherePacking

    out.mkdir(parents=True, exist_ok=True)
    for name, budget in PACKINGS.items():
        mesh = load_mesh(meshes / f"{name}.obj")
        started = time.perf_counter()
        packing = SpherePacking.from_mesh(mesh, max_spheres=budget)
        seconds = time.perf_counter() - started
        path = out / f"{name}.spheres"
        packing.write(path, source=meshes / f"{name}.obj")
        q = packing.quality(mesh)
        print(f"{path.relative_to(HERE.parent)}: {q.count} sphere(s), coverage "
              f"{100 * q.coverage:.1f} %, max outside {1000 * q.max_outside:.2f} mm, "
              f"{seconds:.1f} s")
    # the mug again with the full default budget, for comparison (not written)
    mesh = load_mesh(meshes / "mug.obj")
    q = SpherePacking.from_mesh(mesh, max_spheres=256).quality(mesh)
    print(f"mug with 256 spheres: coverage {100 * q.coverage:.1f} %, "
          f"max outside {1000 * q.max_outside:.2f} mm")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", action="store_true", help="build the meshes only")
    args = parser.parse_args(argv)
    build_meshes()
    if not args.meshes:
        sys.path.insert(0, str(HERE.parent))
        build_packings()
    return 0


if __name__ == "__main__":
    sys.exit(main())
