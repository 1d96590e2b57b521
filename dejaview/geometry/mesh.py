"""Loading meshes, primitive shapes and their mass properties.

Everything here works in the mesh's own frame and in SI units (metres,
kilograms). Meshes are ``trimesh.Trimesh`` objects; this module adds the checks
and repairs a rigid-body simulator needs (a closed surface, outward normals) and
turns every failure into a :class:`dejaview.errors.GeometryError` that names the
file or mesh and the reason.
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from dejaview.errors import GeometryError
from dejaview.geometry import MESH_SUFFIXES

CACHE_ENV = "DEJAVIEW_CACHE_DIR"
CACHE_FOLDER = ".dejaview-cache"
PRIMITIVE_SHAPES = ("box", "sphere", "cylinder")

# Tessellation of primitive meshes: fine enough that volume and inertia are
# within 0.5 % of the closed forms.
_SPHERE_SUBDIVISIONS = 4
_CYLINDER_SECTIONS = 128


@dataclass
class MassProperties:
    """Mass, centre of mass and inertia of a rigid body.

    Attributes:
        mass: kilograms.
        center_of_mass: (3,) position of the centre of mass in the mesh frame, metres.
        inertia: (3, 3) inertia tensor about the centre of mass, axes of the mesh
            frame, kg m^2.
    """

    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray


def file_hash(path) -> str:
    """SHA-256 of a file's bytes, as 64 hex digits (used to key caches).

    Raises:
        GeometryError: the file cannot be read.
    """
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except OSError as exc:
        raise GeometryError(f"{path}: cannot read file: {exc.strerror or exc}") from exc
    return digest.hexdigest()


def cache_folder(mesh_path, cache_dir=None) -> Path:
    """Where results derived from a mesh file are cached.

    ``cache_dir`` if given, else ``$DEJAVIEW_CACHE_DIR`` if set, else a
    ``.dejaview-cache/`` folder beside the mesh.
    """
    if cache_dir is not None:
        return Path(cache_dir)
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    return Path(mesh_path).parent / CACHE_FOLDER


def mesh_hash(mesh: trimesh.Trimesh) -> str:
    """SHA-256 of a mesh's vertex and face arrays (a cache key for meshes not read from a file)."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return digest.hexdigest()


def load_mesh(path) -> trimesh.Trimesh:
    """Read a triangle mesh from an .obj, .stl, .ply or .glb file.

    A file holding a scene (several meshes, node transforms, as glTF does) is
    flattened into one mesh with the transforms applied. Materials, textures
    and normals are dropped and duplicate vertices merged, so a closed surface
    comes out watertight. Nothing is fetched over the network: references to
    other files resolve only inside the mesh file's folder.

    Args:
        path: file name (str or Path).
    Returns:
        The mesh, vertices (V, 3) and faces (F, 3), in the file's units (metres
        by convention).
    Raises:
        GeometryError: missing file, unsupported suffix, unreadable content or
            a file without triangles. The message names the file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise GeometryError(
            f"{path}: unsupported mesh format {suffix or '(no suffix)'!r}; "
            f"use one of {', '.join(MESH_SUFFIXES)}"
        )
    if not path.is_file():
        raise GeometryError(f"{path}: mesh file not found")
    try:
        scene = trimesh.load_scene(
            str(path),
            file_type=suffix[1:],
            # assets resolve only inside the mesh's folder (trimesh's default since 5.0)
            resolver=trimesh.resolvers.FilePathResolver(str(path), allow_anywhere=False),
            allow_remote=False,
        )
        loaded = scene.to_mesh()
    except Exception as exc:  # trimesh raises anything from ValueError to struct.error
        raise GeometryError(f"{path}: cannot read mesh: {exc}") from exc
    if loaded is None or len(loaded.faces) == 0:
        raise GeometryError(f"{path}: the file holds no triangles")
    mesh = trimesh.Trimesh(
        vertices=np.asarray(loaded.vertices, dtype=np.float64),
        faces=np.asarray(loaded.faces, dtype=np.int64),
        process=True,
    )
    if len(mesh.faces) == 0:
        raise GeometryError(f"{path}: the file holds only degenerate triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise GeometryError(f"{path}: the mesh has non-finite vertex coordinates")
    mesh.metadata["file_path"] = str(path)
    mesh.metadata["file_name"] = path.name
    return mesh


def mesh_name(mesh: trimesh.Trimesh) -> str:
    """A name for messages: the mesh's file name if it came from a file, else a summary."""
    name = mesh.metadata.get("file_path") if mesh.metadata else None
    return str(name) if name else f"<mesh with {len(mesh.faces)} faces>"


def primitive_mesh(shape: str, size=None, radius=None, height=None) -> trimesh.Trimesh:
    """Triangle mesh of a scene primitive, centred at the origin.

    Args:
        shape: ``"box"`` (needs ``size``), ``"sphere"`` (needs ``radius``) or
            ``"cylinder"`` (needs ``radius`` and ``height``; axis z).
        size: (3,) full extents x y z of a box, metres.
        radius: sphere or cylinder radius, metres.
        height: cylinder height (full length along z), metres.
    Returns:
        A watertight mesh with outward normals.
    Raises:
        GeometryError: unknown shape, missing or non-positive dimension.
    """
    check_primitive(shape, size, radius, height)
    if shape == "box":
        return trimesh.creation.box(extents=np.asarray(size, dtype=np.float64))
    if shape == "sphere":
        return trimesh.creation.icosphere(subdivisions=_SPHERE_SUBDIVISIONS, radius=float(radius))
    return trimesh.creation.cylinder(
        radius=float(radius), height=float(height), sections=_CYLINDER_SECTIONS
    )


def check_primitive(shape, size=None, radius=None, height=None) -> None:
    """Raise GeometryError unless the shape is known and has the dimensions it needs."""
    if shape not in PRIMITIVE_SHAPES:
        raise GeometryError(
            f"unknown primitive shape {shape!r}; use one of {', '.join(PRIMITIVE_SHAPES)}"
        )
    if shape == "box":
        if size is None:
            raise GeometryError("box: 'size' (x y z extents) is required")
        size = np.asarray(size, dtype=np.float64)
        if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise GeometryError(f"box: size must be three positive numbers, got {size.tolist()}")
    if shape in ("sphere", "cylinder"):
        if radius is None or not np.isfinite(radius) or radius <= 0:
            raise GeometryError(f"{shape}: radius must be a positive number, got {radius!r}")
    if shape == "cylinder":
        if height is None or not np.isfinite(height) or height <= 0:
            raise GeometryError(f"cylinder: height must be a positive number, got {height!r}")


def watertight_mesh(mesh: trimesh.Trimesh, name: str | None = None) -> trimesh.Trimesh:
    """A closed, outward-facing copy of ``mesh``, repaired if it needs it.

    Repairs tried, in order: merging duplicate vertices, removing degenerate and
    duplicate faces, fixing winding and normals, filling holes. A mesh that is
    inside out (negative volume) is inverted.

    Args:
        mesh: any triangle mesh; not modified.
        name: how to call the mesh in error messages (default: its file name).
    Returns:
        A watertight mesh with positive volume.
    Raises:
        GeometryError: the mesh is empty, or still not watertight after repair.
    """
    name = name or mesh_name(mesh)
    if len(mesh.faces) == 0:
        raise GeometryError(f"{name}: the mesh has no triangles")
    fixed = mesh.copy()
    if not fixed.is_watertight or not fixed.is_winding_consistent:
        fixed.merge_vertices()
        fixed.update_faces(fixed.nondegenerate_faces())
        fixed.update_faces(fixed.unique_faces())
        fixed.remove_unreferenced_vertices()
        trimesh.repair.fix_winding(fixed)
        if not fixed.is_watertight:
            trimesh.repair.fill_holes(fixed)
        trimesh.repair.fix_normals(fixed)
    if not fixed.is_watertight:
        raise GeometryError(
            f"{name}: the mesh is not watertight (open edges or non-manifold edges) and "
            "could not be repaired; close its holes in a mesh editor"
        )
    if not fixed.is_winding_consistent:
        raise GeometryError(f"{name}: inconsistent face winding that could not be repaired")
    if fixed.volume < 0:
        fixed.invert()
    if not fixed.volume > 0:
        raise GeometryError(f"{name}: the mesh encloses no volume")
    return fixed


def collision_solid(path, scale: float = 1.0, convex_hull: bool = False) -> tuple[trimesh.Trimesh, bool]:
    """The solid a robot's collision mesh file takes part in contacts as, in the file's frame, scaled.

    The file's mesh made watertight (:func:`watertight_mesh`); where its holes cannot be closed,
    its convex hull, as MuJoCo and Bullet collide meshes. Kept for the process (keyed by the file's
    path, modification time and size): every consumer of one robot loads each mesh once.

    Args:
        path: the mesh file.
        scale: uniform scale applied to the vertices.
        convex_hull: the hull in any case (an MJCF mesh: MuJoCo collides it as its hull).
    Returns:
        (mesh, hull): a watertight mesh with outward normals, vertices (V, 3) and faces (F, 3),
        not to be modified; ``hull`` True where the convex hull stands in for the file's surface.
    Raises:
        GeometryError: a file that cannot be read, or whose hull encloses no volume.
    """
    path = Path(path)
    try:
        stat = path.stat()
    except OSError:
        raise GeometryError(f"{path}: mesh file not found") from None
    return _collision_solid(str(path), stat.st_mtime_ns, stat.st_size, float(scale), bool(convex_hull))


@functools.lru_cache(maxsize=64)
def _collision_solid(path: str, _mtime_ns: int, _size: int, scale: float,
                     convex_hull: bool) -> tuple[trimesh.Trimesh, bool]:
    mesh = load_mesh(path)
    solid = None
    if not convex_hull:
        try:
            solid = watertight_mesh(mesh)
        except GeometryError:  # holes that cannot be closed: the hull, as MuJoCo and Bullet take it
            solid = None
    hull = solid is None
    if hull:
        solid = mesh.convex_hull
        if not solid.volume > 0:
            raise GeometryError(f"{path}: the mesh's convex hull encloses no volume (a flat mesh)")
    if scale != 1.0:
        solid = solid.copy()
        solid.apply_scale(scale)
    return solid, hull


def mass_properties(mesh: trimesh.Trimesh, mass: float | None = None,
                    density: float = 1000.0) -> MassProperties:
    """Mass, centre of mass and inertia of a solid of uniform density bounded by ``mesh``.

    Args:
        mesh: triangle mesh; repaired on a copy if it is not watertight.
        mass: total mass in kg; when given it overrides ``density``.
        density: kg/m^3, used when ``mass`` is None.
    Returns:
        MassProperties with inertia (3, 3) about the centre of mass.
    Raises:
        GeometryError: not watertight after repair, or a non-positive mass/density.
    """
    _check_mass(mass, density, mesh_name(mesh))
    solid = watertight_mesh(mesh)
    props = trimesh.triangles.mass_properties(solid.triangles, density=1.0)  # mass == volume
    volume = float(props.volume)
    if mass is not None:
        density = float(mass) / volume
    inertia = np.asarray(props.inertia, dtype=np.float64) * density
    return MassProperties(
        mass=volume * density,
        center_of_mass=np.asarray(props.center_mass, dtype=np.float64).copy(),
        inertia=0.5 * (inertia + inertia.T),
    )


def primitive_mass_properties(shape: str, size=None, radius=None, height=None,
                              mass: float | None = None,
                              density: float = 1000.0) -> MassProperties:
    """Closed-form mass properties of a primitive centred at the origin.

    Args:
        shape: ``"box"``, ``"sphere"`` or ``"cylinder"`` (axis z).
        size: (3,) box extents x y z, metres.
        radius: sphere or cylinder radius, metres.
        height: cylinder height, metres.
        mass: kg; overrides ``density`` when given.
        density: kg/m^3.
    Returns:
        MassProperties; centre of mass (3,) is zero, inertia (3, 3) is diagonal.
    Raises:
        GeometryError: bad shape or dimensions, non-positive mass or density.
    """
    check_primitive(shape, size, radius, height)
    _check_mass(mass, density, shape)
    if shape == "box":
        x, y, z = (float(v) for v in size)
        volume = x * y * z
    elif shape == "sphere":
        r = float(radius)
        volume = 4.0 / 3.0 * np.pi * r**3
    else:
        r, h = float(radius), float(height)
        volume = np.pi * r**2 * h
    m = float(mass) if mass is not None else volume * density
    if shape == "box":
        diag = m / 12.0 * np.array([y * y + z * z, x * x + z * z, x * x + y * y])
    elif shape == "sphere":
        diag = np.full(3, 0.4 * m * r * r)
    else:
        side = m * (3.0 * r * r + h * h) / 12.0
        diag = np.array([side, side, 0.5 * m * r * r])
    return MassProperties(mass=m, center_of_mass=np.zeros(3), inertia=np.diag(diag))


def _check_mass(mass, density, name) -> None:
    if mass is not None and not (np.isfinite(mass) and mass > 0):
        raise GeometryError(f"{name}: mass must be a positive number, got {mass!r}")
    if mass is None and not (np.isfinite(density) and density > 0):
        raise GeometryError(f"{name}: density must be a positive number, got {density!r}")
