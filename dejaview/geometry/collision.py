"""Exact interpenetration tests between scene objects, with python-fcl.

The simulator sees objects as sphere packings and sampled distance grids;
this module answers "do these two solids overlap, and how deeply?" on the
real geometry, to decide (never to differentiate: fcl has no gradients)
whether a start is feasible and whether a scene's given poses make sense.

How each object is represented:

* ``plane``: the half-space z <= 0 of its frame, handled in closed form
  (the lowest point of the other object along the normal). fcl's
  ``Halfspace`` is not used: its distance queries are known to crash.
* ``box``, ``sphere``, ``cylinder``: fcl primitives (solids).
* a convex mesh: one ``fcl.Convex`` (a solid).
* a non-convex mesh: convex pieces from CoACD (``coacd``, computed once per
  mesh file and cached beside it like sphere packings), each an
  ``fcl.Convex``; and the exact surface as an ``fcl.BVHModel`` plus the
  watertight mesh for inside tests.

Depth of a pair of solids: the largest penetration depth (the shortest
translation that separates them) over all pairs of their convex pieces that
fcl's GJK finds overlapping. The depth of two convex pieces is the smallest
overlap of their projections onto the face normals of both (and, for a
sphere or cylinder, EPA's contact normal): exact unless the deepest
direction is an edge against an edge, where it is a little too deep. (fcl's
own EPA depth is not used for polytopes: it is wrong by tens of percent in
plain cases, see ``overlap.piece_depth``.) Since a body that lies entirely inside
another still overlaps one of its pieces, it is found too; a
surface-crossing test would miss it. For a non-convex mesh the pieces fill
its concavities a little (the mug's cavity and handle hole:
``test_pieces_cover_a_nonconvex_mesh_and_are_cached`` bounds how much), so an overlap
found between pieces is confirmed on the exact geometry: fcl's collision of
the true surfaces (a BVH against the other's solid or surface), or, where
no surfaces cross, whether one object lies inside the other. An overlap
that is only in a filled concavity is no overlap (depth 0); a confirmed one
up to ``REFINE_LIMIT`` deep takes the smaller of the pieces' depth and the
deepest exact contact. For non-convex meshes the depth is thus a close
estimate; the yes/no answer is exact.

Speed: ``docs/benchmarks.md``, "Physics measurements".

Resting contact is not a penetration: a pair counts only where its depth
exceeds ``margin`` (and ``TOUCHING``, fcl's numerical noise).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from dejaview.errors import GeometryError
from dejaview.geometry import DEFAULT_MARGIN
from dejaview.geometry.convex_pieces import load_or_build_pieces
from dejaview.geometry.overlap import below_plane, piece_depth, support, vertex_depth
from dejaview.geometry.transforms import quat_to_matrix

# Depths up to this count as touching: EPA's noise on touching solids is ~1e-16 m,
# tessellated curved surfaces rest on each other to within ~1e-7 m.
TOUCHING = 1e-6
# Pieces' depths up to this are refined with the exact surfaces' contacts (a filled
# concavity can make them too deep by up to its size); deeper ones are far beyond
# any margin and would cost one contact per buried triangle.
REFINE_LIMIT = 0.05
_MAX_CONTACTS = 100_000


# ------------------------------------------------------------------- helpers
def _convex_geometry(mesh: trimesh.Trimesh):
    import fcl

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).astype(np.int64).ravel()
    return fcl.Convex(np.asarray(mesh.vertices, dtype=np.float64), len(mesh.faces), faces)


def _bvh_geometry(mesh: trimesh.Trimesh):
    import fcl

    bvh = fcl.BVHModel()
    bvh.beginModel(len(mesh.vertices), len(mesh.faces))
    bvh.addSubModel(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    bvh.endModel()
    return bvh


def _bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    return centre, float(np.linalg.norm(points - centre, axis=1).max())


@dataclass
class _Body:
    """One scene object as collision geometry (object frame).

    ``pieces``: fcl CollisionObjects of the convex pieces (empty for a plane);
    ``centres`` (P, 3) and ``radii`` (P,) their bounding spheres; ``hull``
    (V, 3) vertices whose convex hull is the object's (meshes and boxes);
    ``shapes``: per piece, ``(vertices (V, 3), face normals (K, 3))`` of a
    polytope or ``None`` for a sphere or cylinder (support in closed form);
    ``exact``: fcl CollisionObject of the true surface (non-convex meshes) or
    None; ``mesh``: the watertight mesh for inside tests (non-convex meshes).
    """

    id: str
    kind: str
    fixed: bool
    rotation: np.ndarray
    position: np.ndarray
    pieces: list = field(default_factory=list)
    centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    radii: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hull: np.ndarray | None = None
    size: tuple = ()
    shapes: list = field(default_factory=list)
    exact: object = None
    mesh: trimesh.Trimesh | None = None

    @property
    def concave(self) -> bool:
        return self.exact is not None

    def bound(self) -> tuple[np.ndarray, float]:
        """Bounding sphere of the whole object: centre (3,) in the object frame, radius."""
        if self.kind == "plane":
            return np.zeros(3), np.inf
        lo = (self.centres - self.radii[:, None]).min(axis=0)
        hi = (self.centres + self.radii[:, None]).max(axis=0)
        centre = 0.5 * (lo + hi)
        return centre, float(np.max(np.linalg.norm(self.centres - centre, axis=1) + self.radii))

    def lowest(self, rotation: np.ndarray, position: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Smallest ``normal . x`` over the solid placed at the given poses.

        Args:
            rotation: (B, 3, 3); position: (B, 3); normal: (3,) unit, world frame.
        Returns:
            (B,) support values, metres.
        """
        base = position @ normal
        n_local = np.einsum("bij,i->bj", rotation, normal)  # normal in the object frame
        if self.kind == "sphere":
            return base - self.size[0]
        if self.kind == "cylinder":
            radius, height = self.size
            along = np.abs(n_local[:, 2])
            return base - 0.5 * height * along - radius * np.sqrt(np.clip(1.0 - along ** 2, 0.0, None))
        return base + (n_local @ self.hull.T).min(axis=1)


def _face_normals(mesh: trimesh.Trimesh) -> np.ndarray:
    """(K, 3) distinct outward face normals of a convex mesh (coplanar triangles once)."""
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    _, first = np.unique(np.round(normals, 9), axis=0, return_index=True)
    return normals[np.sort(first)]


def _body_from_object(scene, obj) -> _Body | None:
    """A scene object's collision geometry (a mesh as CoACD's convex pieces)."""

    def mesh_pieces():
        from dejaview.geometry.mesh import load_mesh, watertight_mesh

        path = scene.resolve(obj.mesh)
        mesh = watertight_mesh(load_mesh(path))
        return mesh, load_or_build_pieces(path, mesh)

    return _body(obj.id, obj.geometry_kind, obj.fixed, obj.pose.orientation, obj.pose.position, obj.size,
                 obj.radius, obj.height, mesh_pieces)


def _body_from_piece(piece) -> _Body | None:
    """A robot link's collision geometry (a ``dejaview.geometry.robot.RobotPiece``, fixed)."""

    def mesh_pieces():  # only ever met by movable objects: its hull covers it
        mesh, hull = piece.solid()
        return mesh, [mesh if hull or mesh.is_convex else mesh.convex_hull]

    return _body(piece.name, piece.kind, True, piece.orientation, piece.position, piece.size, piece.radius,
                 piece.height, mesh_pieces)


def _body(name, kind, fixed, orientation, position, size, radius, height, mesh_pieces) -> _Body | None:
    """Collision geometry of a placed solid; ``mesh_pieces()``: a mesh's (mesh, convex pieces)."""
    import fcl

    rotation = quat_to_matrix(orientation)
    position = np.asarray(position, dtype=np.float64)
    body = _Body(name, kind, fixed, rotation, position)
    if body.kind == "plane":
        return body
    if body.kind == "box":
        sx, sy, sz = (float(v) for v in size)
        geometries = [fcl.Box(sx, sy, sz)]
        half = 0.5 * np.array([sx, sy, sz])
        body.hull = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * half
        body.centres, body.radii = np.zeros((1, 3)), np.array([np.linalg.norm(half)])
        body.shapes = [(body.hull, np.eye(3))]
    elif body.kind == "sphere":
        geometries = [fcl.Sphere(float(radius))]
        body.size = (float(radius),)
        body.centres, body.radii = np.zeros((1, 3)), np.array([float(radius)])
        body.shapes = [None]
    elif body.kind == "cylinder":
        geometries = [fcl.Cylinder(float(radius), float(height))]
        body.size = (float(radius), float(height))
        body.centres = np.zeros((1, 3))
        body.radii = np.array([np.hypot(radius, 0.5 * height)])
        body.shapes = [None]
    elif body.kind == "mesh":
        mesh, pieces = mesh_pieces()
        geometries = [_convex_geometry(p) for p in pieces]
        spheres = [_bounding_sphere(np.asarray(p.vertices)) for p in pieces]
        body.centres = np.array([c for c, _ in spheres])
        body.radii = np.array([r for _, r in spheres])
        body.shapes = [(np.asarray(p.vertices, dtype=np.float64), _face_normals(p)) for p in pieces]
        body.hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
        if len(pieces) > 1 or pieces[0] is not mesh:
            body.exact = fcl.CollisionObject(_bvh_geometry(mesh), fcl.Transform())
            body.mesh = mesh
    else:  # geometry this module does not know (yet): left out of every test
        return None
    body.pieces = [fcl.CollisionObject(g, fcl.Transform(rotation, position)) for g in geometries]
    return body


# -------------------------------------------------------------------- scene
class SceneCollision:
    """Exact interpenetration queries on one scene (build once, query often).

    Every object is placed at its ``<pose>``; :meth:`penetration` moves one
    object to candidate poses, :meth:`interpenetrations` checks the poses as
    given. A robot (``urdf``/``mjcf``) takes part link by link, as fixed
    objects named ``robot-id/link``; a link's non-convex mesh is covered by its
    convex hull instead of CoACD's pieces (seconds to tens of seconds per mesh
    the first time) and confirmed on its surface as any concave mesh: the
    yes/no answer stays exact, the depth is the smaller of the hull's and the
    deepest exact contact. Objects whose geometry is not a plane, box,
    sphere, cylinder or mesh are left out.

    Args:
        scene: a validated ``dejaview.scene.Scene`` (mesh files must exist).
    Raises:
        GeometryError: a mesh that cannot be read, repaired or decomposed
            (the message names the file).
    """

    def __init__(self, scene):
        import fcl

        from dejaview.geometry.robot import robot_pieces

        self.scene = scene
        self._bodies: dict[str, _Body] = {}
        for obj in scene.objects:
            solids = robot_pieces(scene, obj) if obj.robot is not None else [obj]
            for one in solids:
                name = one.id if one is obj else one.name
                try:
                    body = _body_from_object(scene, one) if one is obj else _body_from_piece(one)
                except GeometryError as exc:
                    raise GeometryError(f"object {name!r}: {exc}") from exc
                if body is not None:
                    self._bodies[name] = body
        self._request = fcl.CollisionRequest(num_max_contacts=1, enable_contact=True)
        self._boolean_request = fcl.CollisionRequest(num_max_contacts=1, enable_contact=False)
        self._exact_request = fcl.CollisionRequest(num_max_contacts=_MAX_CONTACTS, enable_contact=True)
        self._scratch = fcl.CollisionResult()  # of boolean requests: their count of contacts decides

    def _overlap(self, g1, g2) -> bool:
        """Do two fcl objects (transforms set) overlap? (One result object, reused.)"""
        import fcl

        found = fcl.collide(g1, g2, self._boolean_request, self._scratch) > 0
        self._scratch.contacts.clear()
        self._scratch.is_collision = False
        return found

    @property
    def ids(self) -> list[str]:
        """Ids of the objects taking part, in file order."""
        return list(self._bodies)

    # -- queries ---------------------------------------------------------------
    def penetration(self, source_id: str, position, orientation, margin: float = 0.0,
                    decide_only: bool = False):
        """Does the source, placed at each candidate pose, interpenetrate another object?

        Every other object stays at its scene pose (fixed and movable alike).

        Args:
            source_id: id of the object to place.
            position: (B, 3) or (3,) where its object-frame origin goes, world frame, m.
            orientation: (B, 4) or (4,) its orientation, w x y z (normalised here).
            margin: depth (m) up to which an overlap counts as resting contact.
            decide_only: only ``hit`` matters (a feasibility check): a candidate's search stops
                at the first overlap that decides it; where ``hit``, ``depth`` is a lower bound
                of the true depth and ``other_id`` the first object found.
        Returns:
            hit (B,) bool: deeper than ``margin`` (and than ``TOUCHING``) into
            some object; depth (B,) float: the deepest overlap with any object
            in metres (0 where none; where it is at most ``margin`` it may be
            an upper bound, since the search for it stops there); other_id: list of B ids of the object
            overlapped most deeply (None where depth is 0). ``hit`` and
            ``depth`` are torch tensors (on ``position``'s device) when
            ``position`` is a tensor, numpy arrays otherwise.
        Raises:
            GeometryError: unknown ``source_id``, or poses of the wrong shape or
                not finite.
        """
        source = self._body(source_id)
        as_torch = _is_tensor(position)
        pos = np.asarray(_to_numpy(position), dtype=np.float64)
        quat = np.asarray(_to_numpy(orientation), dtype=np.float64)
        if pos.ndim == 1:
            pos = pos[None]
        if quat.ndim == 1:
            quat = np.broadcast_to(quat, (len(pos), 4))
        if pos.ndim != 2 or pos.shape[1] != 3 or quat.shape != (len(pos), 4):
            raise GeometryError(f"penetration: position must be (B, 3) and orientation (B, 4), got "
                                f"{tuple(pos.shape)} and {tuple(quat.shape)}")
        if not np.all(np.isfinite(pos)):
            raise GeometryError("penetration: positions must be finite")
        rot = quat_to_matrix(quat)
        limit = max(float(margin), TOUCHING)
        depth, other = self._deepest(source, rot, pos, source_id, limit, decide_only)
        hit = depth > limit
        if as_torch:
            import torch

            device = position.device
            return (torch.as_tensor(hit, device=device), torch.as_tensor(depth, device=device), other)
        return hit, depth, other

    def query_bytes(self, source_id: str) -> int:
        """Bytes a ``penetration`` query holds per candidate pose at its peak: the support values of
        the source's hull vertices against a plane (B, V), beside its rotation, pose and depths
        (docs/benchmarks.md, "Sized before run", has the ball's)."""
        body = self._body(source_id)
        return 8 * ((0 if body.hull is None else len(body.hull)) + 32)

    def ball_penetration(self, source_id: str, position, radius: float):
        """How deep a ball of ``radius`` centred at each position overlaps the objects other than
        ``source_id`` (each at its scene pose).

        A ball inside the source about its object-frame origin (``inner_radius``) lies inside it at
        every orientation, and a solid overlaps at least as deeply as any part of it: the ball's
        depth is a lower bound of the source's at that position, whatever its orientation.

        Args:
            source_id: the object left out (the one the ball stands for).
            position: (B, 3) ball centres, world frame, m.
            radius: m, positive.
        Returns:
            depth (B,) numpy, m (0 where it overlaps nothing); other_id: list of B ids of the object
            overlapped most deeply (None where depth is 0).
        Raises:
            GeometryError: positions of the wrong shape or not finite, a radius that is not positive.
        """
        import fcl

        pos = np.asarray(position, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(pos)) or not (np.isfinite(radius) and radius > 0):
            raise GeometryError("ball_penetration: positions must be finite and the radius positive")
        ball = _Body("<ball>", "sphere", False, np.eye(3), np.zeros(3), size=(float(radius),),
                     centres=np.zeros((1, 3)), radii=np.array([float(radius)]), shapes=[None],
                     pieces=[fcl.CollisionObject(fcl.Sphere(float(radius)), fcl.Transform())])
        rot = np.broadcast_to(np.eye(3), (len(pos), 3, 3))
        return self._deepest(ball, rot, pos, source_id, TOUCHING, decide_only=False)

    def inner_radius(self, object_id: str) -> float:
        """Radius (m) of the largest ball about the object's frame origin that lies inside it
        (0 where the origin is not inside: a mug's origin in its cavity, a plane).

        Raises:
            GeometryError: unknown ``object_id``.
        """
        body = self._body(object_id)
        if body.kind == "sphere":
            return body.size[0]
        if body.kind == "cylinder":
            return min(body.size[0], 0.5 * body.size[1])
        if body.kind == "box":
            return float(np.abs(body.hull).min())
        if body.kind != "mesh":
            return 0.0
        if body.concave:
            from dejaview.geometry.distance import contains, unsigned_distance

            origin = np.zeros((1, 3))
            if not contains(body.mesh, origin)[0]:
                return 0.0
            return float(unsigned_distance(body.mesh, origin)[0][0])
        # a convex mesh is its one piece: the origin's distance to the nearest face plane
        vertices, normals = body.shapes[0]
        return max(0.0, float((vertices @ normals.T).max(axis=0).min()))

    def _deepest(self, a: _Body, rot: np.ndarray, pos: np.ndarray, skip: str, limit: float,
                 decide_only: bool) -> tuple[np.ndarray, list]:
        """Deepest overlap of ``a`` at B poses (rot (B, 3, 3), pos (B, 3)) with every object but
        ``skip``: depth (B,) and the id overlapped most deeply (None where none); ``limit`` and
        ``decide_only`` as in ``penetration``."""
        depth = np.zeros(len(pos))
        other: list[str | None] = [None] * len(pos)
        for body in self._bodies.values():
            if body.id == skip:
                continue
            todo = np.flatnonzero(depth <= limit) if decide_only else np.arange(len(pos))
            d = np.zeros(len(pos))
            d[todo] = self._pair_depths(a, rot[todo], pos[todo], body, limit=limit, decide_only=decide_only)
            deeper = d > depth
            depth[deeper] = d[deeper]
            for i in np.flatnonzero(deeper):
                other[i] = body.id
        return depth, other

    def interpenetrations(self, margin: float = DEFAULT_MARGIN) -> list[tuple[str, str, float]]:
        """Pairs of objects that overlap at their given poses.

        Pairs of two fixed objects are skipped (furniture may stand in the floor).

        Args:
            margin: depth (m) up to which an overlap counts as resting contact.
        Returns:
            (id_a, id_b, depth in m) for each pair deeper than ``margin``, in
            file order of the pair.
        """
        bodies = list(self._bodies.values())
        found = []
        for i, a in enumerate(bodies):
            for b in bodies[i + 1:]:
                if a.fixed and b.fixed:
                    continue
                d = float(self._pair_depths(a, a.rotation[None], a.position[None], b)[0])
                if d > max(float(margin), TOUCHING):
                    found.append((a.id, b.id, d))
        return found

    def is_fixed(self, object_id: str) -> bool:
        """Whether ``object_id`` stands (a fixed object or a robot's link)."""
        return self._body(object_id).fixed

    def depths(self, object_id: str, rotation: np.ndarray, position: np.ndarray, other_id: str) -> np.ndarray:
        """Overlap (B,) in m of ``object_id`` placed at B poses, rotation (B, 3, 3) and position (B, 3)
        of its frame, with ``other_id`` at its scene pose (a moving link's path: ``geometry.sweep``)."""
        return self._pair_depths(self._body(object_id), rotation, position, self._body(other_id))

    # -- pairs -----------------------------------------------------------------
    def _body(self, object_id: str) -> _Body:
        if object_id not in self._bodies:
            known = ", ".join(self._bodies) or "none"
            raise GeometryError(f"no object {object_id!r} with collision geometry (objects: {known})")
        return self._bodies[object_id]

    def _pair_depths(self, a: _Body, rot: np.ndarray, pos: np.ndarray, b: _Body,
                     limit: float | None = None, decide_only: bool = False) -> np.ndarray:
        """Depth of the overlap of ``a`` at B poses with ``b`` at its own pose.

        Args:
            rot: (B, 3, 3), pos: (B, 3): the poses of ``a``.
            limit: only depths above it need be exact (``overlap.piece_depth``).
            decide_only: only whether a depth exceeds ``limit`` matters (``_solid_depth``).
        Returns:
            (B,) depths in metres (0 where they do not overlap).
        """
        if a.kind == "plane" and b.kind == "plane":
            return np.zeros(len(pos))
        if b.kind == "plane":
            return below_plane(a, rot, pos, b.rotation, b.position)
        if a.kind == "plane":
            below = np.empty(len(pos))
            for i in range(len(pos)):
                below[i] = below_plane(b, b.rotation[None], b.position[None], rot[i], pos[i])[0]
            return below
        centre_a, reach_a = a.bound()
        centre_b, reach_b = b.bound()
        gap = np.linalg.norm(pos + rot @ centre_a - (b.rotation @ centre_b + b.position), axis=1)
        depths = np.zeros(len(pos))
        for i in np.flatnonzero(gap < reach_a + reach_b):
            depths[i] = self._solid_depth(a, rot[i], pos[i], b, limit, decide_only)
        return depths

    def _solid_depth(self, a: _Body, rot: np.ndarray, pos: np.ndarray, b: _Body,
                     limit: float | None = None, decide_only: bool = False) -> float:
        """Depth of the overlap of two solids (neither a plane), ``a`` at (rot, pos); ``limit``:
        see ``overlap.piece_depth``. ``decide_only``: only whether the depth exceeds ``limit`` matters.
        The piece pairs are then searched until one overlaps deeper than ``limit`` (convex
        solids) or than ``REFINE_LIMIT`` too (a concave one, whose exact check keeps a pieces'
        depth that deep as it is): that depth, a lower bound of the deepest, decides. A concave
        pair whose pieces overlap by at most ``limit`` skips the exact check, which can only
        make the depth smaller (``_exact_depth``); one whose mesh has a vertex deeper than
        ``limit`` inside a convex polytope is decided by that vertex before any piece is tried
        (``overlap.vertex_depth``: the pieces cover the mesh, so they overlap at least as deeply)."""
        import fcl

        ca = a.centres @ rot.T + pos
        cb = b.centres @ b.rotation.T + b.position
        close = np.linalg.norm(ca[:, None] - cb[None], axis=2) < a.radii[:, None] + b.radii[None]
        pairs = np.argwhere(close)
        if not len(pairs):
            return 0.0
        transform = fcl.Transform(rot, pos)
        deepest = 0.0
        concave = a.concave or b.concave
        enough = np.inf
        if decide_only and limit is not None:
            enough = max(limit, REFINE_LIMIT) if concave else limit
            if concave:  # a vertex deeper than the limit decides at once (the pieces cover the mesh)
                bound = vertex_depth(a, rot, pos, b)
                if bound > limit:
                    return bound
        placed = -1
        for p, q in pairs.tolist():
            piece = a.pieces[p]
            if p != placed:
                piece.setTransform(transform)
                placed = p
            # EPA (a contact) only where a curved piece needs its normal as an axis
            curved = a.shapes[p] is None or b.shapes[q] is None
            if curved:
                result = fcl.CollisionResult()
                if not fcl.collide(piece, b.pieces[q], self._request, result):
                    continue
                contact = result.contacts[0]
            elif self._overlap(piece, b.pieces[q]):
                contact = None
            else:
                continue
            deepest = max(deepest, piece_depth(a, p, rot, pos, b, q, contact, limit))
            if deepest > enough:
                break
        if decide_only and limit is not None and deepest <= limit:
            return deepest
        if deepest > TOUCHING and concave:
            deepest = self._exact_depth(a, rot, pos, b, deepest)
        return deepest

    def _exact_depth(self, a: _Body, rot: np.ndarray, pos: np.ndarray, b: _Body,
                     pieces_depth: float) -> float:
        """The overlap on the true surfaces, given the pieces' depth.

        Returns 0 where the true solids do not overlap (the pieces met in a
        filled concavity); where the surfaces cross and the pieces' depth is
        within ``REFINE_LIMIT``, the smaller of it and the deepest exact
        contact; else the pieces' depth.
        """
        import fcl

        # a convex object's only piece is its exact solid
        geom_a = a.exact if a.concave else a.pieces[0]
        geom_b = b.exact if b.concave else b.pieces[0]
        geom_a.setTransform(fcl.Transform(rot, pos))
        geom_b.setTransform(fcl.Transform(b.rotation, b.position))
        if self._overlap(geom_a, geom_b):
            if pieces_depth > REFINE_LIMIT:
                return pieces_depth
            result = fcl.CollisionResult()
            fcl.collide(geom_a, geom_b, self._exact_request, result)
            # sphere-triangle contacts come with a negative sign
            exact = max((abs(c.penetration_depth) for c in result.contacts), default=pieces_depth)
            return min(pieces_depth, exact)
        # no surfaces cross: disjoint, or one entirely inside the other
        if b.concave and _inside(b, b.rotation, b.position, _any_point(a, rot, pos)):
            return pieces_depth
        if a.concave and _inside(a, rot, pos, _any_point(b, b.rotation, b.position)):
            return pieces_depth
        return 0.0


def _any_point(body: _Body, rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """A point of the solid in the world frame (a surface vertex of meshes, else its centre)."""
    local = np.asarray(body.mesh.vertices[0]) if body.mesh is not None else (
        body.hull[0] if body.kind == "mesh" else np.zeros(3))
    return rot @ local + pos


def _inside(body: _Body, rot: np.ndarray, pos: np.ndarray, point: np.ndarray) -> bool:
    """Whether a world point lies inside a non-convex mesh placed at (rot, pos)."""
    from dejaview.geometry.distance import contains

    local = rot.T @ (point - pos)
    return bool(contains(body.mesh, local[None])[0])


def _is_tensor(value) -> bool:
    return type(value).__module__.startswith("torch")


def _to_numpy(value):
    if _is_tensor(value):
        return value.detach().cpu().double().numpy()
    return value
