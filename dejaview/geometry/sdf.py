"""Signed distance grids of static meshes.

The simulator looks up the distance from a moving body's spheres to static
geometry (tables, counters, shelves) by trilinear interpolation in a regular
grid; it does the differentiable lookup in torch itself. This module builds the
grid (exact distances within two spacings of the surface, a closest-point
transform further out), caches it as ``.npz``, and offers a numpy lookup.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from dejaview.errors import GeometryError
from dejaview.geometry import distance
from dejaview.geometry.mesh import (
    cache_folder,
    file_hash,
    load_mesh,
    mesh_hash,
    mesh_name,
    watertight_mesh,
)

# Bump when the construction changes so that cached grids are rebuilt.
SDF_VERSION = 1
_MAX_NODES = 16_000_000  # about 1.5 GB while building


@dataclass(eq=False)
class SignedDistanceGrid:
    """Signed distance to a closed surface sampled on a regular grid.

    Attributes:
        origin: (3,) position of grid node [0, 0, 0], in the mesh frame, metres.
        spacing: distance between neighbouring nodes, metres.
        values: (nx, ny, nz) float64 signed distances at the nodes, negative
            inside; node [i, j, k] sits at ``origin + spacing * (i, j, k)``.
    """

    origin: np.ndarray
    spacing: float
    values: np.ndarray

    def __post_init__(self):
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.spacing = float(self.spacing)
        self.values = np.asarray(self.values, dtype=np.float64)
        if self.values.ndim != 3 or min(self.values.shape) < 2:
            raise GeometryError(
                f"signed distance grid: values must be (nx, ny, nz) with every n >= 2, "
                f"got shape {self.values.shape}"
            )
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise GeometryError(f"signed distance grid: spacing must be positive, got {self.spacing}")

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nx, ny, nz) node counts."""
        return tuple(int(n) for n in self.values.shape)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) corners of the grid box: first and last node."""
        return np.stack([self.origin, self.origin + self.spacing * (np.array(self.shape) - 1)])

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, spacing: float = 0.01, padding: float = 0.1,
                  cache_dir=None) -> "SignedDistanceGrid":
        """Sample a mesh's signed distance on a grid around it.

        Nodes within two spacings of the surface get exact distances; the rest
        the distance to the closest surface point of their nearest such node
        (an upper bound, a fraction of a spacing off at most).

        Args:
            mesh: closed mesh (repaired on a copy if needed).
            spacing: node spacing, metres.
            padding: margin added around the mesh's bounding box, metres.
            cache_dir: if given, grids are kept there as ``.npz`` files keyed by
                the mesh's vertices and faces and the parameters.
        Returns:
            The grid.
        Raises:
            GeometryError: mesh not closed, bad parameters, or a grid of more
                than 16 million nodes.
        """
        spacing, padding = _check_parameters(spacing, padding)
        cached = None
        if cache_dir is not None:
            cached = Path(cache_dir) / f"sdf-{_cache_key(mesh_hash(mesh), spacing, padding)}.npz"
            grid = _read_cache(cached)
            if grid is not None:
                return grid
        name = mesh_name(mesh)
        solid = watertight_mesh(mesh, name)
        lo, hi = solid.bounds
        extent = np.maximum(np.ceil((hi - lo + 2 * padding) / spacing) + 1, 2)  # floats: no int64 overflow
        nodes = float(np.prod(extent))
        if not nodes <= _MAX_NODES:
            raise GeometryError(
                f"{name}: a signed distance grid at {spacing:g} m spacing would have "
                f"{nodes:.4g} nodes (limit {_MAX_NODES}); use a coarser spacing"
            )
        shape = extent.astype(np.int64)
        # centre the grid on the box so that symmetric meshes give symmetric grids
        origin = 0.5 * (lo + hi) - 0.5 * (shape - 1) * spacing
        values = distance.lattice_signed_distance(solid, origin, spacing, shape,
                                                  band=2.0 * spacing)
        grid = cls(origin, spacing, values)
        if cached is not None:
            _write_cache(grid, cached)
        return grid

    def query(self, points: np.ndarray) -> np.ndarray:
        """Signed distance at arbitrary points by trilinear interpolation.

        Points outside the grid get the value at the nearest point of the grid
        box plus their distance to the box, which stays positive (the box
        boundary lies outside the mesh by the padding).

        Args:
            points: (..., 3) positions in the mesh frame.
        Returns:
            (...,) signed distances, negative inside.
        """
        points = np.asarray(points, dtype=np.float64)
        flat = points.reshape(-1, 3)
        top = np.array(self.shape) - 1
        u = (flat - self.origin) / self.spacing
        clamped = np.clip(u, 0, top)
        base = np.minimum(np.floor(clamped).astype(np.int64), top - 1)
        f = clamped - base
        v = self.values
        i, j, k = base[:, 0], base[:, 1], base[:, 2]
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        c00 = v[i, j, k] * (1 - fx) + v[i + 1, j, k] * fx
        c10 = v[i, j + 1, k] * (1 - fx) + v[i + 1, j + 1, k] * fx
        c01 = v[i, j, k + 1] * (1 - fx) + v[i + 1, j, k + 1] * fx
        c11 = v[i, j + 1, k + 1] * (1 - fx) + v[i + 1, j + 1, k + 1] * fx
        c0 = c00 * (1 - fy) + c10 * fy
        c1 = c01 * (1 - fy) + c11 * fy
        value = c0 * (1 - fz) + c1 * fz
        outside = np.linalg.norm((u - clamped) * self.spacing, axis=1)
        return (value + outside).reshape(points.shape[:-1])

    def save(self, path) -> None:
        """Write the grid as a compressed ``.npz`` (origin, spacing, values, version)."""
        try:
            with open(path, "wb") as handle:
                np.savez_compressed(handle, origin=self.origin, spacing=np.float64(self.spacing),
                                    values=self.values, version=np.int64(SDF_VERSION))
        except OSError as exc:
            raise GeometryError(f"{path}: cannot write signed distance grid: {exc}") from exc

    @classmethod
    def load(cls, path) -> "SignedDistanceGrid":
        """Read a grid written by :meth:`save`.

        Raises:
            GeometryError: missing, unreadable or malformed file.
        """
        try:
            with np.load(path, allow_pickle=False) as data:
                if int(data["version"]) != SDF_VERSION:
                    raise GeometryError(
                        f"{path}: signed distance grid version {int(data['version'])}, "
                        f"expected {SDF_VERSION}"
                    )
                return cls(data["origin"], float(data["spacing"]), data["values"])
        except FileNotFoundError:
            raise GeometryError(f"{path}: signed distance grid file not found") from None
        except GeometryError:
            raise
        except Exception as exc:  # zipfile, KeyError, ValueError from a damaged file
            raise GeometryError(f"{path}: not a signed distance grid: {exc}") from exc


def load_or_build_sdf(mesh_path, spacing: float = 0.01, padding: float = 0.1,
                      cache_dir=None, convex_hull: bool = False) -> SignedDistanceGrid:
    """The signed distance grid of a mesh file, from the cache or built and cached.

    Args:
        mesh_path: the mesh file.
        spacing, padding: as in :meth:`SignedDistanceGrid.from_mesh`.
        cache_dir: cache folder (default: ``$DEJAVIEW_CACHE_DIR`` if set, else
            ``.dejaview-cache/`` beside the mesh). Keyed by the file's SHA-256.
        convex_hull: the grid of the mesh's convex hull (a robot's mesh with holes,
            ``dejaview.geometry.mesh.collision_solid``).
    Returns:
        The grid.
    """
    spacing, padding = _check_parameters(spacing, padding)
    mesh_path = Path(mesh_path)
    if not mesh_path.is_file():
        raise GeometryError(f"{mesh_path}: mesh file not found")
    key = _cache_key(file_hash(mesh_path), spacing, padding, convex_hull)
    kind = "hull-sdf" if convex_hull else "sdf"
    cached = cache_folder(mesh_path, cache_dir) / f"{mesh_path.stem}-{kind}-{key}.npz"
    grid = _read_cache(cached)
    if grid is None:
        mesh = load_mesh(mesh_path)
        grid = SignedDistanceGrid.from_mesh(mesh.convex_hull if convex_hull else mesh, spacing=spacing,
                                            padding=padding)
        _write_cache(grid, cached)
    return grid


def _check_parameters(spacing, padding) -> tuple[float, float]:
    if not (np.isfinite(spacing) and spacing > 0):
        raise GeometryError(f"signed distance grid: spacing must be a positive length, got {spacing!r}")
    if not (np.isfinite(padding) and padding >= 0):
        raise GeometryError(f"signed distance grid: padding must be >= 0, got {padding!r}")
    return float(spacing), float(padding)


def _cache_key(digest: str, spacing: float, padding: float, convex_hull: bool = False) -> str:
    fields = {"mesh": digest, "spacing": spacing, "padding": padding, "version": SDF_VERSION}
    if convex_hull:  # only then: the keys of grids already cached stay as they were
        fields["hull"] = True
    text = json.dumps(fields, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _read_cache(path: Path) -> SignedDistanceGrid | None:
    if not path.is_file():
        return None
    try:
        return SignedDistanceGrid.load(path)
    except GeometryError as exc:
        warnings.warn(f"ignoring a broken cached grid ({exc}); rebuilding", stacklevel=3)
        return None


def _write_cache(grid: SignedDistanceGrid, path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        grid.save(partial)
        os.replace(partial, path)
    except (OSError, GeometryError) as exc:
        warnings.warn(f"could not cache the signed distance grid in {path.parent}: {exc}",
                      stacklevel=3)
