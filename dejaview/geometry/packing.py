"""Sphere packings: rigid bodies approximated by unions of spheres.

A packing is built in the spirit of ProtoSphere (Weller and Zachmann, 2010):
the interior of the mesh is sampled on a regular lattice with signed distances
to the surface; a sphere centred on an interior node may reach ``tolerance``
beyond the surface; spheres are inserted greedily, each time the one that
covers the most interior nodes not yet covered, until the sphere budget, the
minimum radius or the coverage target stops it. The radius of every chosen
sphere is then set from the exact distance of its centre to the surface, so no
sphere reaches more than ``tolerance`` outside the mesh.

Primitive boxes are packed from their shape instead
(``dejaview.geometry.box_spheres``): spheres touching faces, edges and corners,
mirror-symmetric. The lattice and the greedy cover are in
``dejaview.geometry.greedy_cover``.

Packings live in ``.spheres`` files (see the scene format): ``#`` comments, one
``x y z r`` line per sphere, in the mesh's frame, metres.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from dejaview.errors import GeometryError
from dejaview.geometry import distance
from dejaview.geometry.box_spheres import box_spheres
from dejaview.geometry.greedy_cover import greedy_cover, interior_lattice
from dejaview.geometry.mesh import (
    cache_folder,
    check_primitive,
    file_hash,
    load_mesh,
    mesh_name,
    primitive_mesh,
    watertight_mesh,
)

# Bump when the algorithm changes so that cached packings are rebuilt.
ALGORITHM = "greedy-coverage-1"
BOX_ALGORITHM = "box-faces-1"  # the primitive box's packing (box_spheres)
MAX_TOLERANCE = 0.002  # metres: no sphere may reach further outside its mesh



@dataclass
class PackingQuality:
    """How well a packing matches its mesh.

    Attributes:
        count: number of spheres.
        coverage: fraction (0..1) of the mesh volume inside the union of spheres.
        max_outside: how far the union reaches outside the mesh, metres: the
            largest ``r - depth(center)``, depth positive inside. Negative when
            every sphere stays inside.
        volume: mesh volume, m^3.
        min_radius: smallest sphere radius, metres.
        max_radius: largest sphere radius, metres.
        samples: interior sample points used for ``coverage``.
        max_gap: how far the mesh's surface lies from the union of spheres,
            metres: the largest distance from a surface point to the nearest
            sphere (0 where a sphere covers it), over the mesh's vertices, edge
            midpoints and ``surface_samples`` random surface points (a lower
            bound of the true largest gap, tight to the sample spacing).
            With ``max_outside`` it bounds the distance between the packing's
            surface and the mesh's.
    """

    count: int
    coverage: float
    max_outside: float
    volume: float
    min_radius: float
    max_radius: float
    samples: int
    max_gap: float = 0.0

    @property
    def max_deviation(self) -> float:
        """The largest distance between the packing's surface and the mesh's, metres."""
        return max(self.max_outside, self.max_gap)


@dataclass(eq=False)
class SpherePacking:
    """A union of spheres approximating a rigid body, in the body mesh's frame.

    Attributes:
        centers: (N, 3) float64 sphere centres, metres.
        radii: (N,) float64 radii, metres, all positive.
        header: metadata written as ``# key: value`` comments (source mesh, its
            hash, the packing parameters).
    """

    centers: np.ndarray
    radii: np.ndarray
    header: dict[str, str] = field(default_factory=dict)

    def __post_init__(self):
        self.centers = np.array(self.centers, dtype=np.float64).reshape(-1, 3)
        self.radii = np.array(self.radii, dtype=np.float64).reshape(-1)
        if len(self.centers) != len(self.radii):
            raise GeometryError(
                f"sphere packing: {len(self.centers)} centres but {len(self.radii)} radii"
            )
        if not (np.all(np.isfinite(self.centers)) and np.all(np.isfinite(self.radii))):
            raise GeometryError("sphere packing: non-finite centre or radius")
        if np.any(self.radii <= 0):
            raise GeometryError("sphere packing: radii must be positive")
        self.header = {str(k): str(v) for k, v in dict(self.header).items()}

    def __len__(self) -> int:
        return len(self.radii)

    # ----------------------------------------------------------------- building
    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, max_spheres: int = 256,
                  min_radius: float | None = None, coverage: float | None = None,
                  resolution: float | None = None, tolerance: float = 0.001,
                  progress: Callable[[int, int], None] | None = None) -> "SpherePacking":
        """Pack a closed mesh with spheres, greedily by newly covered volume.

        Args:
            mesh: the body's surface; repaired on a copy if not watertight.
            max_spheres: sphere budget.
            min_radius: no sphere smaller than this, metres (default: no limit).
            coverage: stop once this fraction (0..1] of the interior is covered
                (measured on the lattice; default: use the whole budget).
            resolution: lattice spacing in metres (default: chosen per shape,
                20 000 to 300 000 interior nodes, finer for thin shapes).
            tolerance: how far a sphere may reach outside the surface, metres
                (0 to 0.002).
            progress: called as ``progress(done, total)`` after each sphere.
        Returns:
            The packing; ``header`` records the parameters.
        Raises:
            GeometryError: bad parameters, or a mesh that is not closed or is
                thinner than the lattice.
        """
        settings = _settings(max_spheres, min_radius=min_radius, coverage=coverage,
                             resolution=resolution, tolerance=tolerance)
        name = mesh_name(mesh)
        solid = watertight_mesh(mesh, name)
        triangles = distance.triangle_array(solid)

        spacing, origin, shape, inside, values = interior_lattice(triangles, solid, resolution,
                                                                  tolerance, name)
        if values is None:
            values = distance.lattice_signed_distance(triangles, origin, spacing, shape,
                                                      band=spacing)
        index = np.flatnonzero(inside.ravel())
        points = origin + np.stack(np.unravel_index(index, shape), axis=1) * spacing
        reach = -values.ravel()[index] + tolerance

        chosen = greedy_cover(points, reach, spacing, settings["max_spheres"],
                              min_radius or 0.0, coverage, progress)
        centers = points[chosen]
        # exact radii: the lattice distances far from the surface are upper bounds
        exact, _ = distance.unsigned_distance(triangles, centers)
        radii = exact + tolerance
        keep = radii >= max(min_radius or 0.0, 1e-9)
        if not keep.any():
            raise GeometryError(
                f"{name}: no sphere fits" + (f" with a radius of at least {min_radius:g} m"
                                             if min_radius else "")
            )
        header = {
            "generator": f"dejaview {ALGORITHM}",
            "mesh": Path(name).name if mesh.metadata.get("file_path") else name,
            "spheres": str(int(keep.sum())),
            **{k: _format_setting(k, v) for k, v in settings.items()},
            "lattice_spacing": f"{spacing:.6g}",
        }
        return cls(centers[keep], radii[keep], header)

    @classmethod
    def from_primitive(cls, shape: str, size=None, radius=None, height=None,
                       **params) -> "SpherePacking":
        """Packing of a scene primitive centred at the origin.

        A sphere is exactly one sphere. A box gets spheres touching its faces,
        edges and corners, mirror-symmetric about its three mid-planes, with the
        box's extent (``dejaview.geometry.box_spheres``), as many as
        ``max_spheres`` allows; ``min_radius`` sets the radius of its edges'
        spheres, ``tolerance`` does not apply (no sphere reaches outside), and
        ``resolution`` or ``coverage``, or a budget too small for that
        construction, pack it from its mesh like a cylinder. A cylinder is
        packed from its mesh with ``from_mesh(**params)``.

        Args:
            shape: ``"box"``, ``"sphere"`` or ``"cylinder"`` (axis z).
            size: (3,) box extents; radius, height: as in the scene format.
            **params: as in :meth:`from_mesh`.
        Returns:
            The packing.
        Raises:
            GeometryError: bad dimensions or parameters.
        """
        check_primitive(shape, size, radius, height)
        if shape == "sphere":
            return cls(np.zeros((1, 3)), [float(radius)],
                       {"generator": "dejaview primitive", "mesh": f"sphere r={radius}"})
        name = (f"box size={' '.join(str(float(v)) for v in size)}"
                if shape == "box" else f"cylinder r={radius} h={height}")
        if shape == "box" and params.get("resolution") is None and params.get("coverage") is None:
            settings = _settings(params.get("max_spheres", 256), min_radius=params.get("min_radius"),
                                 tolerance=params.get("tolerance", 0.001))
            built = box_spheres(size, settings["max_spheres"],
                                edge_radius=settings["min_radius"] or None)
            if built is not None:
                header = {"generator": f"dejaview {BOX_ALGORITHM}", "mesh": name,
                          "spheres": str(len(built[1])), "max_spheres": str(settings["max_spheres"])}
                return cls(built[0], built[1], header)
        packing = cls.from_mesh(primitive_mesh(shape, size=size, radius=radius, height=height),
                                **params)
        packing.header["mesh"] = name
        return packing

    # -------------------------------------------------------------- file format
    @classmethod
    def read(cls, path) -> "SpherePacking":
        """Read a ``.spheres`` file.

        Args:
            path: file name.
        Returns:
            The packing; ``# key: value`` comment lines fill ``header``.
        Raises:
            GeometryError: missing or unreadable file, a line that is not four
                numbers, a non-finite number, a non-positive radius (message
                ``file:line: reason``), or no spheres at all.
        """
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise GeometryError(f"{path}: sphere packing file not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise GeometryError(f"{path}: cannot read sphere packing: {exc}") from exc
        header: dict[str, str] = {}
        rows: list[list[float]] = []
        for number, line in enumerate(text.splitlines(), start=1):
            stripped = line.strip()
            if not stripped:
                continue
            if stripped.startswith("#"):
                key, colon, value = stripped[1:].partition(":")
                if colon and key.strip() and " " not in key.strip():
                    header[key.strip()] = value.strip()
                continue
            fields = stripped.split()
            if len(fields) != 4:
                raise GeometryError(
                    f"{path}:{number}: expected 4 numbers 'x y z r', got {len(fields)} "
                    f"field{'s' if len(fields) != 1 else ''}: {stripped[:60]!r}"
                )
            try:
                values = [float(f) for f in fields]
            except ValueError:
                bad = next(f for f in fields if not _is_float(f))
                raise GeometryError(f"{path}:{number}: not a number: {bad!r}") from None
            if not all(math.isfinite(v) for v in values):
                raise GeometryError(f"{path}:{number}: non-finite number in {stripped!r}")
            if values[3] <= 0:
                raise GeometryError(f"{path}:{number}: radius must be positive, got {fields[3]}")
            rows.append(values)
        if not rows:
            raise GeometryError(f"{path}: the file holds no spheres")
        data = np.array(rows, dtype=np.float64)
        return cls(data[:, :3], data[:, 3], header)

    def write(self, path, source=None) -> None:
        """Write a ``.spheres`` file with a header comment.

        Args:
            path: file to write (its folder must exist).
            source: the mesh file this packing was made from; its name (relative
                to the packing's folder) and SHA-256 go into the header.
        """
        path = Path(path)
        header = dict(self.header)
        if source is not None:
            source = Path(source)
            try:
                shown = os.path.relpath(source.resolve(), path.parent.resolve())
            except ValueError:  # another drive on Windows
                shown = str(source.resolve())
            if Path(shown).parts[:3] == ("..",) * 3:
                shown = str(source.resolve())  # far away: an absolute name reads better
            header = {"source": shown.replace(os.sep, "/"), "sha256": file_hash(source),
                      **{k: v for k, v in header.items() if k not in ("source", "sha256", "mesh")}}
        header["spheres"] = str(len(self))
        lines = ["# DejaView sphere packing: one sphere per line, 'x y z r' in metres, "
                 "in the mesh's frame"]
        lines += [f"# {key}: {value}" for key, value in header.items()]
        lines += [f"{x!r} {y!r} {z!r} {r!r}"
                  for (x, y, z), r in zip(self.centers.tolist(), self.radii.tolist())]
        try:
            path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        except OSError as exc:
            raise GeometryError(f"{path}: cannot write sphere packing: {exc}") from exc

    # ------------------------------------------------------------------ queries
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """A small sphere enclosing every sphere of the packing.

        Within about 1 % of the smallest enclosing sphere (Badoiu-Clarkson
        iterations from the box centre).

        Returns:
            center (3,) and radius.
        """
        lo = (self.centers - self.radii[:, None]).min(axis=0)
        hi = (self.centers + self.radii[:, None]).max(axis=0)
        center = 0.5 * (lo + hi)

        def enclosing(c):
            return float(np.max(np.linalg.norm(self.centers - c, axis=1) + self.radii))

        best_center, best_radius = center.copy(), enclosing(center)
        for step in range(1, 400):
            offset = self.centers - center
            reach = np.linalg.norm(offset, axis=1) + self.radii
            far = int(np.argmax(reach))
            length = np.linalg.norm(offset[far])
            direction = offset[far] / length if length > 0 else np.zeros(3)
            center = center + (self.centers[far] + self.radii[far] * direction - center) / (step + 1)
            radius = enclosing(center)
            if radius < best_radius:
                best_center, best_radius = center.copy(), radius
        return best_center, best_radius

    def quality(self, mesh: trimesh.Trimesh, samples: int = 200_000,
                seed: int = 0, surface_samples: int = 20_000) -> PackingQuality:
        """Measure coverage of and overreach beyond ``mesh``.

        Coverage is estimated on a randomly jittered lattice (one random point
        per cell, about ``samples`` of them inside the mesh): the fraction of
        interior points inside some sphere. Overreach is exact; the gap is
        measured at surface samples.

        Args:
            mesh: the mesh the packing approximates, in the same frame.
            samples: about how many interior points to test.
            seed: random seed of the jitter and the surface samples.
            surface_samples: random surface points where the gap is measured
                (besides every vertex and edge midpoint).
        Returns:
            PackingQuality.
        """
        solid = watertight_mesh(mesh)
        triangles = distance.triangle_array(solid)
        volume = float(solid.volume)
        spacing = (volume / max(int(samples), 1)) ** (1.0 / 3.0)
        lo, hi = solid.bounds
        counts = np.maximum(np.ceil((hi - lo) / spacing).astype(np.int64), 1)
        rng = np.random.default_rng(seed)
        ii, jj = np.meshgrid(np.arange(counts[0]), np.arange(counts[1]), indexing="ij")
        cells = np.stack([ii.ravel(), jj.ravel()], axis=1)
        xy = lo[:2] + (cells + rng.random(cells.shape)) * spacing
        z0 = lo[2] + rng.random(len(cells)) * spacing
        inside = distance.column_inside(triangles, xy, z0, spacing, int(counts[2]))
        column, level = np.nonzero(inside)
        points = np.column_stack([xy[column], z0[column] + level * spacing])
        covered = np.zeros(len(points), dtype=bool)
        if len(points) and len(self):
            tree = cKDTree(points)
            for hits in tree.query_ball_point(self.centers, self.radii, return_sorted=False):
                covered[hits] = True
        depth = distance.depth(triangles, self.centers) if len(self) else np.zeros(0)
        return PackingQuality(
            count=len(self),
            coverage=float(covered.mean()) if len(points) else 0.0,
            max_outside=float(np.max(self.radii - depth)) if len(self) else 0.0,
            volume=volume,
            min_radius=float(self.radii.min()) if len(self) else 0.0,
            max_radius=float(self.radii.max()) if len(self) else 0.0,
            samples=len(points),
            max_gap=self._max_gap(solid, surface_samples, rng),
        )

    def _max_gap(self, mesh: trimesh.Trimesh, count: int, rng) -> float:
        """Largest distance (m) from the mesh surface to the union of spheres, at samples."""
        if not len(self):
            return float(np.max(np.ptp(mesh.bounds, axis=0)))
        edges = mesh.vertices[mesh.edges_unique].mean(axis=1)
        tri = np.asarray(mesh.triangles)
        area = np.asarray(mesh.area_faces)
        face = rng.choice(len(tri), size=int(count), p=area / area.sum())
        u, v = rng.random((2, int(count)))
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        random = tri[face, 0] + u[:, None] * (tri[face, 1] - tri[face, 0]) + v[:, None] * (
            tri[face, 2] - tri[face, 0])
        points = np.concatenate([np.asarray(mesh.vertices), edges, random])
        gap = np.full(len(points), np.inf)
        for start in range(0, len(points), 4096):  # bounded (4096, spheres) temporaries
            chunk = points[start:start + 4096]
            d = np.linalg.norm(chunk[:, None] - self.centers[None], axis=2) - self.radii[None]
            gap[start:start + 4096] = d.min(axis=1)
        return float(max(0.0, gap.max()))


def load_or_build_packing(mesh_path, spheres_path=None, max_spheres: int = 256,
                          cache_dir=None, **params) -> SpherePacking:
    """The packing of a mesh file: read, from the cache, or built (and cached).

    Order: ``spheres_path`` if given and the file exists (with a warning if its
    header records another mesh hash); else a cached packing with the same mesh
    hash and parameters; else a new one from :meth:`SpherePacking.from_mesh`,
    written to the cache.

    Args:
        mesh_path: the mesh file.
        spheres_path: an explicit ``.spheres`` file (the scene's ``spheres=``).
        max_spheres: sphere budget.
        cache_dir: cache folder (default: ``$DEJAVIEW_CACHE_DIR`` if set, else
            ``.dejaview-cache/`` beside the mesh).
        **params: ``min_radius``, ``coverage``, ``resolution``, ``tolerance``,
            ``progress`` as in :meth:`SpherePacking.from_mesh`.
    Returns:
        The packing.
    Raises:
        GeometryError: unreadable mesh or packing file, bad parameters.
    """
    mesh_path = Path(mesh_path)
    if spheres_path is not None and Path(spheres_path).is_file():
        packing = SpherePacking.read(spheres_path)
        recorded = packing.header.get("sha256", "").lower()
        # hand-written files may carry anything there: compare real digests only
        if (re.fullmatch(r"[0-9a-f]{64}", recorded) and mesh_path.is_file()
                and recorded != file_hash(mesh_path)):
            warnings.warn(f"{spheres_path} was made from another version of {mesh_path} "
                          "(its sha256 differs); rebuild it with 'dejaview pack'", stacklevel=2)
        return packing
    if not mesh_path.is_file():
        raise GeometryError(f"{mesh_path}: mesh file not found")
    progress = params.pop("progress", None)
    settings = _settings(max_spheres, **params)
    digest = file_hash(mesh_path)
    key = hashlib.sha256(
        json.dumps({"mesh": digest, "algorithm": ALGORITHM, **settings},
                   sort_keys=True).encode()
    ).hexdigest()[:16]
    folder = cache_folder(mesh_path, cache_dir)
    cached = folder / f"{mesh_path.stem}-{key}.spheres"
    if cached.is_file():
        try:
            return SpherePacking.read(cached)
        except GeometryError as exc:
            warnings.warn(f"ignoring a broken cached packing ({exc}); rebuilding", stacklevel=2)
    packing = SpherePacking.from_mesh(load_mesh(mesh_path), max_spheres=max_spheres,
                                      progress=progress, **params)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        partial = cached.with_name(f"{cached.name}.{os.getpid()}.tmp")
        packing.write(partial, source=mesh_path)
        os.replace(partial, cached)
    except (OSError, GeometryError) as exc:
        warnings.warn(f"could not cache the sphere packing in {folder}: {exc}", stacklevel=2)
    return packing


def _settings(max_spheres, min_radius=None, coverage=None, resolution=None,
              tolerance=0.001) -> dict:
    """Validated packing parameters (the cache key and the file header)."""
    if isinstance(max_spheres, bool) or int(max_spheres) != max_spheres or max_spheres < 1:
        raise GeometryError(f"max_spheres must be a positive integer, got {max_spheres!r}")
    if min_radius is not None and not (math.isfinite(min_radius) and min_radius >= 0):
        raise GeometryError(f"min_radius must be a non-negative length, got {min_radius!r}")
    if coverage is not None and not (0 < coverage <= 1):
        raise GeometryError(f"coverage must be in (0, 1], got {coverage!r}")
    if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
        raise GeometryError(f"resolution must be a positive length, got {resolution!r}")
    if not (math.isfinite(tolerance) and 0 <= tolerance <= MAX_TOLERANCE):
        raise GeometryError(
            f"tolerance must be between 0 and {MAX_TOLERANCE} m, got {tolerance!r}"
        )
    return {"max_spheres": int(max_spheres), "min_radius": min_radius, "coverage": coverage,
            "resolution": resolution, "tolerance": float(tolerance)}


def _format_setting(name: str, value) -> str:
    if value is None:
        return "auto" if name == "resolution" else "none"
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
