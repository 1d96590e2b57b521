"""Geometry: meshes, sphere packings and signed distance grids.

Modules (import them directly; this package imports nothing, so that
``import dejaview`` stays free of trimesh):

* ``dejaview.geometry.mesh``: ``load_mesh``, ``primitive_mesh``,
  ``mass_properties``, ``primitive_mass_properties``, ``file_hash``;
* ``dejaview.geometry.packing``: ``SpherePacking``, ``load_or_build_packing``;
  it builds with ``greedy_cover`` (meshes) and ``box_spheres`` (primitive boxes);
* ``dejaview.geometry.sdf``: ``SignedDistanceGrid``, ``load_or_build_sdf``;
* ``dejaview.geometry.distance``: inside tests and exact distances on lattices;
* ``dejaview.geometry.collision``: ``SceneCollision`` (exact interpenetration
  tests with python-fcl);
* ``dejaview.geometry.convex_pieces``: ``load_or_build_pieces`` (convex
  decomposition with CoACD, cached);
* ``dejaview.geometry.transforms``: rigid transforms in numpy (quaternions w x y z);
* ``dejaview.geometry.robot``: URDF and MJCF robot files, read and posed.
"""

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb")
"""Mesh file suffixes read (``load_mesh``): what a scene's ``mesh=`` and a URDF's meshes may name."""

DEFAULT_MARGIN = 0.002
"""Overlap (m) that ``dejaview validate`` and ``SceneCollision.interpenetrations`` accept as resting
contact: the sphere packings reach up to 1 mm outside a surface, and an object left at rest by the
simulator sinks a fraction of a millimetre into what it rests on. Here, not in ``collision``: the
CLI's ``--help`` reads it without loading trimesh."""
