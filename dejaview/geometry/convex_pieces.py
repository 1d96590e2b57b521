"""Convex decomposition of meshes (CoACD), cached beside the mesh like sphere packings.

``dejaview.geometry.collision`` tests interpenetration on these pieces with
python-fcl; ``dejaview.io.mjcf`` exports a non-convex mesh to MuJoCo as them.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path

import numpy as np
import trimesh

from dejaview.errors import GeometryError

# CoACD settings: no remeshing (keeps the surface exact), fixed seed (same pieces
# every time), a lighter tree search than the default (faster, for pieces as good:
# ``test_pieces_cover_a_nonconvex_mesh_and_are_cached`` in tests/geometry/test_collision.py bounds
# their extra volume and how far they reach out).
COACD_SETTINGS = {"threshold": 0.05, "preprocess_mode": "off", "mcts_iterations": 60,
                  "mcts_nodes": 10, "seed": 0}
PIECES_VERSION = 1


def convex_pieces(mesh: trimesh.Trimesh, name: str | None = None) -> list[trimesh.Trimesh]:
    """A closed mesh as a union of convex pieces.

    Args:
        mesh: a watertight triangle mesh (its own frame).
        name: what to call it in messages.
    Returns:
        ``[mesh]`` if it is convex, else CoACD's pieces (convex hulls, in the
        mesh frame), which cover the mesh and fill part of its concavities.
    Raises:
        GeometryError: CoACD fails or returns nothing.
    """
    if mesh.is_convex:
        return [mesh]
    import coacd

    coacd.set_log_level("error")
    try:
        parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices, dtype=np.float64),
                                           np.asarray(mesh.faces, dtype=np.int64)),
                                **COACD_SETTINGS)
    except Exception as exc:  # a C++ exception surfaces as RuntimeError or worse
        raise GeometryError(f"{name or 'mesh'}: convex decomposition failed: {exc}") from exc
    pieces = [trimesh.Trimesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)).convex_hull
              for v, f in parts]
    pieces = [p for p in pieces if p.volume > 0]
    if not pieces:
        raise GeometryError(f"{name or 'mesh'}: convex decomposition returned no pieces")
    return pieces


def load_or_build_pieces(mesh_path, mesh: trimesh.Trimesh | None = None,
                         cache_dir=None) -> list[trimesh.Trimesh]:
    """Convex pieces of a mesh file, from the cache or computed and cached.

    Args:
        mesh_path: the mesh file.
        mesh: the file's mesh if already loaded (watertight).
        cache_dir: cache folder (default: ``$DEJAVIEW_CACHE_DIR`` if set, else
            ``.dejaview-cache/`` beside the mesh). Keyed by the file's SHA-256
            and the decomposition settings.
    Returns:
        The pieces, as in :func:`convex_pieces`.
    """
    from dejaview.geometry.mesh import cache_folder, file_hash, load_mesh, watertight_mesh

    mesh_path = Path(mesh_path)
    if mesh is None:
        mesh = watertight_mesh(load_mesh(mesh_path))
    if mesh.is_convex:
        return [mesh]
    text = json.dumps({"mesh": file_hash(mesh_path), "coacd": COACD_SETTINGS,
                       "version": PIECES_VERSION}, sort_keys=True)
    key = hashlib.sha256(text.encode()).hexdigest()[:16]
    cached = cache_folder(mesh_path, cache_dir) / f"{mesh_path.stem}-pieces-{key}.npz"
    if cached.is_file():
        try:
            with np.load(cached) as data:
                n = int(data["count"])
                return [trimesh.Trimesh(data[f"v{i}"], data[f"f{i}"], process=False)
                        for i in range(n)]
        except Exception as exc:  # a damaged or partial cache file
            warnings.warn(f"ignoring a broken cached decomposition {cached} ({exc}); rebuilding",
                          stacklevel=2)
    pieces = convex_pieces(mesh, name=str(mesh_path))
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        partial = cached.with_name(f"{cached.name}.{os.getpid()}.tmp.npz")
        arrays = {"count": np.asarray(len(pieces))}
        for i, p in enumerate(pieces):
            arrays[f"v{i}"] = np.asarray(p.vertices)
            arrays[f"f{i}"] = np.asarray(p.faces)
        np.savez(partial, **arrays)
        os.replace(partial, cached)
    except OSError as exc:
        warnings.warn(f"could not cache the convex decomposition in {cached.parent}: {exc}",
                      stacklevel=2)
    return pieces
