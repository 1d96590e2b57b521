"""The ``warp`` backend: NVIDIA Warp's ``warp.sim`` (warp-lang 1.9.1) behind the backend interface.

Imported only when asked for (``make_problem(scene, "warp")``); needs the
``warp`` extra (``pip install 'dejaview[warp]'``). Runs on Warp's ``cuda``
device when there is one, else on ``cpu`` (kernels are compiled by Warp's
bundled clang on first use and kept in its kernel cache). ``warp.sim``
computes in float32; the parameters, the decode of the ``ParameterLayout``
and the reported losses stay float64 in torch.

Model (``WarpSimulator.from_scene``), from the same scene as the sphere
simulator:

- movable objects are bodies with DejaView's mass properties
  (``dejaview.geometry.mesh``: the same mass, centre of mass and inertia in
  both backends); their shapes carry no mass of their own;
- shapes: meshes as ``wp.sim.Mesh`` (vertices and faces as trimesh loads
  them), box and sphere as Warp primitives, cylinders as meshes
  (``warp.sim`` generates no cylinder contacts), planes as infinite static
  planes; fixed objects are static shapes (body -1);
- friction and restitution per shape from the object or the scene (Warp
  averages the two shapes of a contact; the sphere simulator takes the
  geometric mean of the frictions), gravity, ``dt`` and ``duration`` from the
  scene.

Settings (backend attributes of ``<simulation>``, or options of
``make_problem(scene, "warp", ...)`` which win):

- ``warp-integrator``: ``xpbd`` (default, as in the original work:
  ``wp.sim.XPBDIntegrator``, no torsional or rolling friction) |
  ``semi-implicit`` (``wp.sim.SemiImplicitIntegrator``: penalty contacts
  whose stiffness is set from the lightest body, ``k = m (0.1 / h)^2``,
  damping from the scene's restitution, Warp's smoothed Coulomb friction);
- ``warp-substeps``: integrator substeps per step (default 1 for XPBD, 10
  for semi-implicit, whose explicit contacts need h ~ 0.2 ms); contacts are
  generated once per step (``wp.sim.collide``) with a 5 cm margin;
- ``warp-iterations`` (default 2): XPBD constraint iterations;
- ``warp-restitution`` (``true`` | ``false``, default false): XPBD's
  restitution pass. Off by default, so XPBD contacts are inelastic whatever
  the scene's restitution: in Warp 1.9.1 that pass breaks reverse mode
  (measured on ``ball_rolled.xml``: gradients up to 10^4 x the central
  difference, with the fix below; exactly zero without it).

Known limits of ``warp.sim`` that this backend inherits (measured):
mesh bodies roll like the polyhedra they are (the example ball, an
icosphere of 642 vertices, loses ~40 % of its rolling speed in 1 s where an
exact sphere keeps it); the semi-implicit friction divides by a quadratic of
the slip speed, so gradients through sticking contacts can overflow float32
to NaN (the optimiser loop then counts that candidate as infinitely bad);
contact-free and frictionless segments give gradients that match central
differences in both integrators.

Loss and gradients: the per-record loss (``pose``: centre-of-mass distance and
``orientation_weight`` x geodesic angle in quadrature; ``position``: origin distance;
``add``: mean model-point distance; plus the target's velocity terms; all
pseudo-Huber smoothed exactly as ``dejaview.losses``) is computed by a Warp
kernel after every step; ``evaluate="final"`` (or a pinned target time)
takes the last record, ``"best"`` the minimum over the records (step 0
included), whose gradient goes to that record alone, as torch's ``amin``
does. Gradients with respect to the source's initial pose and velocities
come from ``wp.Tape`` (reverse mode only; ``gradient="forward"`` is an
error), and are chained through the layout's decode in torch. ``<penalty>``
terms are not supported.

Batches: K candidates run as K replicated environments of one Warp model
(each environment's bodies in their own collision group, the static shapes
shared), in chunks of at most ``max_envs`` environments (default 8; a
reverse pass keeps every step's contacts, so memory grows with chunk x steps).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from dejaview.errors import InferenceError, SceneError

INTEGRATORS = ("xpbd", "semi-implicit")
SIM_EXTRAS = {"warp-integrator": str, "warp-substeps": int, "warp-iterations": int, "warp-restitution": bool}
CONTACT_MARGIN = 0.05  # m; speculative contacts found once per step must cover a step's motion
DEFAULT_SUBSTEPS = {"xpbd": 1, "semi-implicit": 10}
SEMI_IMPLICIT_OMEGA_H = 0.1  # contact frequency x substep of the semi-implicit penalty contacts
LOSS_KINDS = {"pose": 0, "position": 1, "add": 2}


def _import_warp():
    """``warp`` with ``warp.sim``, initialised without its banner and notices.

    Warp prints its deprecation notice for ``warp.sim`` on stdout and, on
    machines without a CUDA driver, a notice on stderr; the CLI keeps both
    streams for results and errors.
    """
    import warp as wp

    wp.config.quiet = True
    with contextlib.redirect_stdout(io.StringIO()):
        import warp.sim  # noqa: F401
        saved = os.dup(2)
        try:
            with open(os.devnull, "w") as null:
                os.dup2(null.fileno(), 2)
                wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
    return wp


wp = _import_warp()


# ------------------------------------------------------------------ kernels
@wp.func
def _smooth(sq: float, eps: float):
    # pseudo-Huber of a squared norm, as dejaview.losses.pose._smooth
    return wp.sqrt(sq + eps * eps) - eps


@wp.kernel
def _record_loss(body_q: wp.array(dtype=wp.transform), body_qd: wp.array(dtype=wp.spatial_vector),
                 source: int, num_bodies: int, record: int, kind: int,
                 target_origin: wp.vec3, target_rot: wp.quat, com: wp.vec3,
                 orientation_weight: float, eps: float, points: wp.array(dtype=wp.vec3),
                 velocity_weight: float, use_linear: int, target_linear: wp.vec3,
                 use_angular: int, target_angular: wp.vec3,
                 losses: wp.array2d(dtype=float)):
    """Loss of env k's source at one record; thread (k, m) adds model point m's share."""
    k, m = wp.tid()
    X = body_q[k * num_bodies + source]
    origin = wp.transform_get_translation(X)
    rot = wp.transform_get_rotation(X)
    c = origin + wp.quat_rotate(rot, com)
    target_c = target_origin + wp.quat_rotate(target_rot, com)
    num_points = points.shape[0]
    if kind == 2:
        p = points[m]
        d = wp.quat_rotate(rot, p) - wp.quat_rotate(target_rot, p) + c - target_c
        wp.atomic_add(losses, record, k, _smooth(wp.dot(d, d), eps) / float(num_points))
    if m == 0:
        value = float(0.0)
        if kind == 0:
            dc = c - target_c
            rel = wp.quat_inverse(target_rot) * rot
            sq = rel[0] * rel[0] + rel[1] * rel[1] + rel[2] * rel[2]
            angle = 2.0 * wp.atan2(wp.sqrt(sq + 1.0e-30), wp.abs(rel[3]))
            a = _smooth(wp.dot(dc, dc), eps)
            b = orientation_weight * _smooth(angle * angle, eps)
            value = wp.sqrt(a * a + b * b + 1.0e-30)
        if kind == 1:
            do = origin - target_origin
            value = _smooth(wp.dot(do, do), eps)
        qd = body_qd[k * num_bodies + source]
        if use_linear != 0:
            dv = wp.spatial_bottom(qd) - target_linear
            value = value + velocity_weight * _smooth(wp.dot(dv, dv), eps)
        if use_angular != 0:
            dw = wp.spatial_top(qd) - target_angular
            value = value + velocity_weight * orientation_weight * _smooth(wp.dot(dw, dw), eps)
        wp.atomic_add(losses, record, k, value)


@wp.kernel
def _copy(src: wp.array(dtype=Any), dest: wp.array(dtype=Any)):
    i = wp.tid()
    dest[i] = src[i]


_CLONE_LOCK = threading.Lock()  # the patched wp.clone is process-wide: one taped simulate at a time


@contextlib.contextmanager
def _tape_safe_clones(state_in):
    """``wp.clone`` inside ``XPBDIntegrator.simulate`` without wiping gradients.

    On a ``wp.Tape``, Warp 1.9.1 records ``wp.copy`` with an adjoint that
    *overwrites* the source's gradient with the copy's: XPBD's restitution
    clones the input state first, so in the reverse pass the clone's adjoint
    comes last and erases every gradient reaching the input state (measured:
    exactly zero gradients through any step with restitution). Here clones of
    the input state are kernel copies (adjoint: accumulate), and the other
    clones (buffers that a kernel overwrites next) are not recorded at all.
    """
    tracked = {id(state_in.body_q), id(state_in.body_qd)}
    original = wp.clone

    def clone(src, device=None, requires_grad=None, pinned=None):
        dest = wp.empty_like(src, device=device, requires_grad=requires_grad)
        if id(src) in tracked:
            wp.launch(_copy, dim=src.shape[0], inputs=[src], outputs=[dest], device=dest.device)
        else:
            tape, wp.context.runtime.tape = wp.context.runtime.tape, None
            try:
                wp.copy(dest, src)
            finally:
                wp.context.runtime.tape = tape
        return dest

    with _CLONE_LOCK:
        wp.clone = clone
        try:
            yield
        finally:
            wp.clone = original


# ----------------------------------------------------------------- settings
def warp_settings(scene, integrator: str | None = None, substeps: int | None = None,
                  iterations: int | None = None, restitution: bool | None = None) -> dict:
    """The backend attributes of ``<simulation>`` (see the module docstring), overridden by options.

    Raises:
        SceneError: a bad attribute value; InferenceError: a bad option.
    """
    where = dict(file=str(scene.path) if scene.path else None, element="simulation")
    extra = scene.simulation.extra
    out = {"integrator": "xpbd", "substeps": None, "iterations": 2, "restitution": False}
    for key, kind in SIM_EXTRAS.items():
        if key not in extra:
            continue
        text = extra[key]
        name = key.removeprefix("warp-")
        if kind is bool:
            if text not in ("true", "false"):
                raise SceneError(f"simulation attribute {key}={text!r} must be true or false", **where)
            out[name] = text == "true"
            continue
        if kind is str:
            if text not in INTEGRATORS:
                raise SceneError(f"simulation attribute {key}={text!r}: choose one of {', '.join(INTEGRATORS)}",
                                 **where)
            out[name] = text
            continue
        try:
            value = int(text)
        except ValueError:
            value = 0
        if value < 1:
            raise SceneError(f"simulation attribute {key}={text!r} must be a positive integer", **where)
        out[name] = value
    for name, value in (("integrator", integrator), ("substeps", substeps), ("iterations", iterations),
                        ("restitution", restitution)):
        if value is None:
            continue
        if name == "restitution":
            out[name] = bool(value)
            continue
        if name == "integrator" and value not in INTEGRATORS:
            raise InferenceError(f"unknown warp integrator {value!r}; choose one of {', '.join(INTEGRATORS)}")
        if name != "integrator" and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise InferenceError(f"warp {name} must be a positive integer, got {value!r}")
        out[name] = value
    if out["substeps"] is None:
        out["substeps"] = DEFAULT_SUBSTEPS[out["integrator"]]
    return out


def default_device() -> str:
    """``cuda`` when Warp sees a CUDA device, else ``cpu``."""
    return "cuda" if wp.is_cuda_available() else "cpu"


# -------------------------------------------------------------------- model
def _wp_quat(q) -> tuple[float, float, float, float]:
    """w x y z (scene) -> x y z w (Warp), normalised."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return (float(x), float(y), float(z), float(w))


def _quat_multiply(a, b) -> np.ndarray:
    """Hamilton product of w x y z quaternions (numpy)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


@dataclass
class BodyFrames:
    """What trajectory writers and ``dejaview.losses`` read of a world: names, centres of mass.

    Attributes:
        names: (N,) movable body ids in scene order.
        com: (N, 3) centre of mass in each object frame.
    """

    names: tuple[str, ...]
    com: torch.Tensor

    @property
    def dtype(self) -> torch.dtype:
        return self.com.dtype

    @property
    def device(self) -> torch.device:
        return self.com.device

    def body_index(self, name: str) -> int:
        return self.names.index(name)

    def object_position(self, state) -> torch.Tensor:
        """Object-frame origins (B, N, 3) of a State whose positions are centres of mass."""
        from dejaview.sim.rotation import quat_rotate

        return state.position - quat_rotate(state.orientation, self.com.expand_as(state.position))


@dataclass
class _Body:
    name: str
    mass: float
    inertia: np.ndarray
    com: np.ndarray
    shape: tuple  # (kind, params) for _add_shape
    friction: float
    restitution: float
    position: np.ndarray
    orientation: np.ndarray  # w x y z
    linear: np.ndarray
    angular: np.ndarray


@dataclass
class _Static:
    name: str
    shape: tuple
    friction: float
    restitution: float
    position: np.ndarray
    orientation: np.ndarray


def _shape_of(scene, obj) -> tuple:
    """("mesh", (vertices, faces)) | ("box", half) | ("sphere", r) | ("plane", None)."""
    from dejaview.geometry.mesh import load_mesh, primitive_mesh

    if obj.mesh is not None:
        mesh = load_mesh(scene.resolve(obj.mesh))
        return "mesh", (np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    if obj.shape == "plane":
        return "plane", None
    if obj.shape == "box":
        return "box", 0.5 * np.asarray(obj.size, dtype=np.float64)
    if obj.shape == "sphere":
        return "sphere", float(obj.radius)
    mesh = primitive_mesh("cylinder", radius=obj.radius, height=obj.height)
    return "mesh", (np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))


@dataclass
class _Batch:
    """One Warp model of ``envs`` replicated environments, with its state buffers."""

    model: object
    integrator: object
    envs: int
    states: dict = field(default_factory=dict)  # (requires_grad, count) -> list of wp.sim.State


class WarpSimulator:
    """A scene as ``warp.sim`` models (one per batch size), and rollouts of them.

    Attributes:
        names: (N,) movable body ids; frames: their ``BodyFrames``.
        dt, duration_steps, settings (integrator, substeps, iterations), device.
    """

    def __init__(self, scene, bodies: list[_Body], statics: list[_Static], settings: dict, device: str):
        self.scene = scene
        self.bodies = bodies
        self.statics = statics
        self.settings = settings
        self.device = device
        self.dt = float(scene.simulation.dt)
        self.duration_steps = scene.simulation.steps
        self.gravity = np.asarray(scene.gravity, dtype=np.float32)
        self.names = tuple(b.name for b in bodies)
        self.frames = BodyFrames(self.names, torch.tensor(np.stack([b.com for b in bodies]), dtype=torch.float64))
        self._batches: dict[int, _Batch] = {}
        self._meshes: dict[int, object] = {}

    @classmethod
    def from_scene(cls, scene, device: str | None = None, **options) -> "WarpSimulator":
        """Build from a scene (``options``: integrator, substeps, iterations; see ``warp_settings``).

        Raises:
            SceneError: no movable object, a movable plane, or a geometry problem.
        """
        from dejaview.errors import GeometryError
        from dejaview.geometry.mesh import load_mesh, mass_properties, primitive_mass_properties

        settings = warp_settings(scene, **options)
        sim = scene.simulation
        bodies, statics = [], []
        for obj in scene.objects:
            where = dict(file=str(scene.path) if scene.path else None, line=obj.line, element="object")
            friction = sim.friction if obj.friction is None else obj.friction
            restitution = sim.restitution if obj.restitution is None else obj.restitution
            try:
                if obj.fixed and obj.robot is not None:  # a robot: one static per link geometry
                    from dejaview.geometry.robot import link_objects

                    statics.extend(_Static(p.id, _shape_of(scene, p), friction, restitution,
                                           np.asarray(p.pose.position, dtype=np.float64),
                                           np.asarray(p.pose.orientation, dtype=np.float64))
                                   for p in link_objects(scene, obj))
                    continue
                shape = _shape_of(scene, obj)
                if obj.fixed:
                    statics.append(_Static(obj.id, shape, friction, restitution,
                                           np.asarray(obj.pose.position, dtype=np.float64),
                                           np.asarray(obj.pose.orientation, dtype=np.float64)))
                    continue
                if shape[0] == "plane":
                    raise SceneError(f"object {obj.id!r}: a plane must be fixed", **where)
                density = obj.density if obj.density is not None else 1000.0
                if obj.mesh is not None:
                    props = mass_properties(load_mesh(scene.resolve(obj.mesh)), mass=obj.mass, density=density)
                else:
                    size = tuple(obj.size) if obj.size is not None else None
                    props = primitive_mass_properties(obj.shape, size=size, radius=obj.radius,
                                                      height=obj.height, mass=obj.mass, density=density)
            except GeometryError as exc:
                raise SceneError(f"object {obj.id!r}: {exc}", **where) from exc
            bodies.append(_Body(obj.id, float(props.mass), np.asarray(props.inertia, dtype=np.float64),
                                np.asarray(props.center_of_mass, dtype=np.float64), shape, friction,
                                restitution, np.asarray(obj.pose.position, dtype=np.float64),
                                np.asarray(obj.pose.orientation, dtype=np.float64),
                                np.asarray(obj.velocity.linear, dtype=np.float64),
                                np.asarray(obj.velocity.angular, dtype=np.float64)))
        if not bodies:
            raise SceneError("the scene has no movable object to simulate",
                             file=str(scene.path) if scene.path else None, element="scene")
        return cls(scene, bodies, statics, settings, device or default_device())

    # ------------------------------------------------------------- building
    @property
    def substep(self) -> float:
        return self.dt / self.settings["substeps"]

    def _wp_mesh(self, vertices_faces):
        key = id(vertices_faces[0])
        if key not in self._meshes:
            v, f = vertices_faces
            self._meshes[key] = wp.sim.Mesh(v.tolist(), f.reshape(-1).tolist(), compute_inertia=False)
        return self._meshes[key]

    def _add_shape(self, builder, body: int, shape: tuple, pos, rot, material: dict, group: int) -> int:
        kind, params = shape
        common = dict(collision_group=group, has_ground_collision=False, **material)
        if kind == "mesh":
            return builder.add_shape_mesh(body, pos=pos, rot=rot, mesh=self._wp_mesh(params), density=0.0,
                                          **common)
        if kind == "box":
            hx, hy, hz = (float(v) for v in params)
            return builder.add_shape_box(body, pos=pos, rot=rot, hx=hx, hy=hy, hz=hz, density=0.0, **common)
        if kind == "sphere":
            return builder.add_shape_sphere(body, pos=pos, rot=rot, radius=params, density=0.0, **common)
        # a Warp plane's normal is its local +y; the scene's is +z: turn +y onto +z, then pose it
        del common["has_ground_collision"]
        return builder.add_shape_plane(pos=pos, rot=rot, width=0.0, length=0.0, body=body, **common)

    def _materials(self) -> dict:
        """Contact stiffness of the semi-implicit integrator (XPBD ignores them)."""
        if self.settings["integrator"] != "semi-implicit":
            return {}
        m = min(b.mass for b in self.bodies)
        omega = SEMI_IMPLICIT_OMEGA_H / self.substep
        e = max(min(self.scene.simulation.restitution, 0.999), 1e-3)
        zeta = -math.log(e) / math.sqrt(math.pi ** 2 + math.log(e) ** 2)
        return {"ke": m * omega ** 2, "kd": 2.0 * zeta * m * omega, "kf": 0.5 * m / self.substep}

    def _build(self, envs: int) -> _Batch:
        builder = wp.sim.ModelBuilder(up_vector=(0.0, 0.0, 1.0), gravity=0.0)
        builder.rigid_contact_margin = CONTACT_MARGIN
        # XPBD's extra torsional (0.5 mu) and rolling (0.001 mu) friction: neither the scene format
        # nor the sphere simulator has them
        builder.rigid_contact_torsional_friction = 0.0
        builder.rigid_contact_rolling_friction = 0.0
        stiffness = self._materials()
        for k in range(envs):
            for b in self.bodies:
                body = builder.add_body(origin=wp.transform(wp.vec3(*b.position), wp.quat(*_wp_quat(b.orientation))),
                                        m=b.mass, I_m=wp.mat33(*b.inertia.reshape(-1).tolist()),
                                        com=wp.vec3(*b.com), name=f"{b.name}/{k}")
                self._add_shape(builder, body, b.shape, wp.vec3(0.0, 0.0, 0.0), wp.quat_identity(),
                                dict(mu=b.friction, restitution=b.restitution, **stiffness), k + 1)
        # statics after the bodies: warp.sim pairs a group with group -1 only when the -1 shape comes later
        static_shapes = []
        for st in self.statics:
            q = st.orientation
            if st.shape[0] == "plane":
                q = _quat_multiply(q, (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0))
            static_shapes.append(self._add_shape(
                builder, -1, st.shape, wp.vec3(*st.position), wp.quat(*_wp_quat(q)),
                dict(mu=st.friction, restitution=st.restitution, **stiffness), -1))
        for a in static_shapes:  # static pairs never move: no contacts between them
            for b in static_shapes:
                if a < b:
                    builder.shape_collision_filter_pairs.add((a, b))
        model = builder.finalize(device=self.device, requires_grad=True)
        model.ground = False
        model.gravity = self.gravity
        if self.settings["integrator"] == "xpbd":
            # (warp.sim's restitution pass fails on a model that can have no contact at all)
            integrator = wp.sim.XPBDIntegrator(
                iterations=self.settings["iterations"],
                enable_restitution=self.settings["restitution"] and model.rigid_contact_max > 0)
        else:
            integrator = wp.sim.SemiImplicitIntegrator(angular_damping=0.0, friction_smoothing=0.01)
        return _Batch(model, integrator, envs)

    def batch(self, envs: int) -> _Batch:
        """The model of ``envs`` environments (built once per size)."""
        if envs not in self._batches:
            self._batches[envs] = self._build(envs)
        return self._batches[envs]

    def _states(self, batch: _Batch, count: int, grad: bool) -> list:
        key = (grad, count)
        if key not in batch.states:
            batch.states = {k: v for k, v in batch.states.items() if k[0] != grad}  # one list per mode
            batch.states[key] = [batch.model.state(requires_grad=grad) for _ in range(count)]
        return batch.states[key]

    # -------------------------------------------------------------- initial
    def base_state(self, envs: int) -> tuple[np.ndarray, np.ndarray]:
        """body_q (envs, N, 7: origin, x y z w) and body_qd (envs, N, 6: angular, linear) of the scene."""
        q = np.array([[*b.position, *_wp_quat(b.orientation)] for b in self.bodies], dtype=np.float64)
        qd = np.array([[*b.angular, *b.linear] for b in self.bodies], dtype=np.float64)
        return np.repeat(q[None], envs, 0), np.repeat(qd[None], envs, 0)

    # -------------------------------------------------------------- rollout
    def run(self, body_q: np.ndarray, body_qd: np.ndarray, steps: int, record_every: int = 1,
            loss=None, grad: bool = False):
        """Simulate a chunk of environments.

        Args:
            body_q: (E, N, 7) initial origins and x y z w quaternions.
            body_qd: (E, N, 6) initial angular and linear (centre-of-mass) velocities, world frame.
            steps: number of steps of ``dt``.
            record_every: keep every k-th state (the first and the last always).
            loss: ``_LossSpec`` to evaluate after every step (records 0..steps), or None.
            grad: record on a ``wp.Tape`` (returned) for a reverse pass.
        Returns:
            (record steps list, body_q records (T, E, N, 7), body_qd records (T, E, N, 6),
            losses wp.array (steps + 1, E) or None, tape or None, first State).
        """
        envs = body_q.shape[0]
        batch = self.batch(envs)
        model, integrator = batch.model, batch.integrator
        sub = self.settings["substeps"]
        h = self.substep
        states = self._states(batch, steps * sub + 1, grad)
        n = len(self.bodies)
        states[0].body_q.assign(wp.array(body_q.reshape(envs * n, 7).astype(np.float32), dtype=wp.transform,
                                         device=self.device))
        states[0].body_qd.assign(wp.array(body_qd.reshape(envs * n, 6).astype(np.float32),
                                          dtype=wp.spatial_vector, device=self.device))
        losses = None
        if loss is not None:
            losses = wp.zeros((steps + 1, envs), dtype=float, device=self.device, requires_grad=grad)
        tape = wp.Tape() if grad else None
        kept, qs, qds = [], [], []

        def record(t):
            state = states[t * sub]
            if loss is not None:
                loss.launch(state, t, envs, n, losses)
            if t % record_every == 0 or t == steps:
                # now: without a tape, XPBD uses its input state as scratch space
                kept.append(t)
                qs.append(state.body_q.numpy().reshape(envs, n, 7).copy())
                qds.append(state.body_qd.numpy().reshape(envs, n, 6).copy())

        with tape if grad else contextlib.nullcontext():
            record(0)
            for t in range(steps):
                wp.sim.collide(model, states[t * sub], requires_grad=grad)
                for s in range(sub):
                    i = t * sub + s
                    states[i].clear_forces()
                    with _tape_safe_clones(states[i]) if grad else contextlib.nullcontext():
                        integrator.simulate(model, states[i], states[i + 1], h)
                record(t + 1)
        qs = np.stack(qs).astype(np.float64)
        qds = np.stack(qds).astype(np.float64)
        return kept, qs, qds, losses, tape, states[0]

    def trajectory(self, kept, qs, qds):
        """A ``Trajectory`` (states (T, E, N, ...), centres of mass, w x y z) of ``run``'s records."""
        from dejaview.sim.integrate import Trajectory
        from dejaview.sim.rotation import quat_rotate
        from dejaview.sim.state import State

        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
        q = t(qs[..., [6, 3, 4, 5]])
        q = q / q.norm(dim=-1, keepdim=True)
        origin = t(qs[..., :3])
        com = origin + quat_rotate(q, self.frames.com.expand_as(origin))
        state = State(com, q, t(qds[..., 3:]), t(qds[..., :3]))
        return Trajectory(state, torch.tensor(kept), self.dt)


def simulate_scene(scene, *, steps: int | None = None, record_every: int = 1, device: str | None = None,
                   **options):
    """Run a scene forward in Warp from its objects' given poses and velocities.

    Needs no ``<inference>`` section (what ``dejaview simulate`` does with the sphere simulator).

    Args:
        scene: a Scene or a path to a scene file.
        steps: number of steps (default: duration / dt).
        record_every: record every k-th step (the first and the last always).
        device, options: as ``WarpSimulator.from_scene`` (integrator, substeps, iterations, restitution).
    Returns:
        (BodyFrames, Trajectory with states (T, 1, N, ...)); write it with
        ``dejaview.io.trajectory.write_trajectory_csv(path, frames, trajectory)``.
    """
    from dejaview.scene import Scene

    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    sim = WarpSimulator.from_scene(scene, device=device, **options)
    q, qd = sim.base_state(1)
    kept, qs, qds, *_ = sim.run(q, qd, sim.duration_steps if steps is None else int(steps),
                                record_every=record_every)
    return sim.frames, sim.trajectory(kept, qs, qds)


@dataclass
class _LossSpec:
    """The numbers of the loss kernel (see ``_record_loss``)."""

    source: int
    kind: int
    target_origin: tuple
    target_rot: tuple  # x y z w
    com: tuple
    orientation_weight: float
    eps: float
    points: object  # wp.array of vec3 (one dummy point unless ``add``)
    velocity_weight: float
    target_linear: tuple | None
    target_angular: tuple | None

    def launch(self, state, record: int, envs: int, num_bodies: int, losses) -> None:
        wp.launch(_record_loss, dim=(envs, self.points.shape[0]),
                  inputs=[state.body_q, state.body_qd, self.source, num_bodies, record, self.kind,
                          wp.vec3(*self.target_origin), wp.quat(*self.target_rot), wp.vec3(*self.com),
                          self.orientation_weight, self.eps, self.points, self.velocity_weight,
                          int(self.target_linear is not None), wp.vec3(*(self.target_linear or (0.0, 0.0, 0.0))),
                          int(self.target_angular is not None),
                          wp.vec3(*(self.target_angular or (0.0, 0.0, 0.0)))],
                  outputs=[losses], device=losses.device)


class WarpProblem:
    """A scene's inference problem on Warp: the backend interface of ``dejaview.backends``.

    Attributes:
        sim: the WarpSimulator.
        layout: ParameterLayout of the source (shared definition with the spheres backend).
        source: index of the source among the movable bodies.
        target, loss_kind, evaluate, steps (loss horizon), orientation_weight, velocity_weight.
        max_envs: most candidates simulated as one Warp model.
        evaluations: loss evaluations so far.
    """

    backend = "warp"
    gradient_modes = ("reverse",)

    def __init__(self, sim: WarpSimulator, layout, source: int, target, loss_kind: str, evaluate: str,
                 steps: int, orientation_weight: float, velocity_weight: float, points, max_envs: int):
        self.sim = sim
        self.layout = layout
        self.source = source
        self.target = target
        self.loss_kind = loss_kind
        self.evaluate = evaluate
        self.steps = steps
        self.orientation_weight = orientation_weight
        self.velocity_weight = velocity_weight
        self.max_envs = max_envs
        self.record_every = 1
        self.evaluations = 0
        self._points = points

    @classmethod
    def from_scene(cls, scene, *, integrator: str | None = None, substeps: int | None = None,
                   iterations: int | None = None, restitution: bool | None = None,
                   device: str | None = None, max_envs: int = 8,
                   orientation_weight: float | None = None, max_speed: float = 3.0,
                   max_spin: float = 10.0) -> "WarpProblem":
        """Build the problem of a scene's ``<inference>``.

        Args:
            scene: a Scene.
            integrator, substeps, iterations, restitution: override the ``warp-*`` attributes
                (module docstring).
            device: Warp device (default ``cuda`` if present, else ``cpu``).
            max_envs: most candidates per Warp model.
            orientation_weight: metres per radian (default as ``dejaview.losses``).
        Raises:
            InferenceError: as ``InferenceProblem.from_scene``, plus ``<penalty>`` terms.
        """
        from dejaview.inference.params import layout_from_scene
        from dejaview.inference.problem import check_inference
        from dejaview.losses.pose import DEFAULT_ORIENTATION_WEIGHT, SMOOTH_EPS
        from dejaview.losses.trajectory import DEFAULT_VELOCITY_WEIGHT

        inf = check_inference(scene)
        if inf.penalties:
            raise InferenceError("the warp backend does not support <penalty> terms; use --backend spheres")
        if isinstance(max_envs, bool) or not isinstance(max_envs, int) or max_envs < 1:
            raise InferenceError(f"max_envs must be a positive integer, got {max_envs!r}")
        sim = WarpSimulator.from_scene(scene, device=device, integrator=integrator, substeps=substeps,
                                       iterations=iterations, restitution=restitution)
        if inf.source not in sim.names:
            raise InferenceError(f"source {inf.source!r} is not a movable object")
        layout = layout_from_scene(scene, dtype=torch.float64, max_speed=max_speed, max_spin=max_spin)
        if layout.size == 0:
            raise InferenceError("no free parameter: the start area pins the position and nothing else is free")
        steps = sim.duration_steps
        if inf.target.time is not None:
            steps = max(1, int(round(inf.target.time / sim.dt)))
        problem = cls(sim, layout, sim.names.index(inf.source), inf.target, inf.loss, inf.evaluate, steps,
                      DEFAULT_ORIENTATION_WEIGHT if orientation_weight is None else orientation_weight,
                      DEFAULT_VELOCITY_WEIGHT, None, max_envs)
        points = np.zeros((1, 3), dtype=np.float32)
        if inf.loss == "add":
            from dejaview.inference.problem import model_points

            points = model_points(scene, scene.object(inf.source)).numpy().astype(np.float32)
        problem._points = wp.array(points, dtype=wp.vec3, device=sim.device)
        problem._eps = SMOOTH_EPS
        return problem

    # ------------------------------------------------------------ interface
    @property
    def num_params(self) -> int:
        return self.layout.size

    @property
    def dtype(self) -> torch.dtype:
        return torch.float64

    @property
    def dt(self) -> float:
        return self.sim.dt

    @property
    def body_names(self) -> tuple[str, ...]:
        return self.sim.names

    @property
    def duration_steps(self) -> int:
        return self.sim.duration_steps

    def __repr__(self) -> str:
        s = self.sim.settings
        return (f"WarpProblem({self.sim.names}, source={self.source}, P={self.num_params}, "
                f"{s['integrator']}, {s['substeps']} substep(s), device={self.sim.device})")

    def simulation_settings(self) -> dict:
        """Simulation numbers for result.json."""
        return {"dt": self.sim.dt, "steps": self.steps, "device": self.sim.device, **self.sim.settings}

    def _loss_spec(self) -> _LossSpec:
        t = self.target
        body = self.sim.bodies[self.source]
        return _LossSpec(source=self.source, kind=LOSS_KINDS[self.loss_kind],
                         target_origin=tuple(map(float, t.position)), target_rot=_wp_quat(t.orientation),
                         com=tuple(map(float, body.com)), orientation_weight=float(self.orientation_weight),
                         eps=float(self._eps), points=self._points, velocity_weight=float(self.velocity_weight),
                         target_linear=None if t.linear_velocity is None else tuple(map(float, t.linear_velocity)),
                         target_angular=None if t.angular_velocity is None else tuple(map(float, t.angular_velocity)))

    def _source_state(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """Decoded source state (K, ...) with a unit quaternion."""
        s = self.layout.decode(x)
        q = s["orientation"]
        return {**s, "orientation": q / q.norm(dim=-1, keepdim=True)}

    def _initial(self, s: dict[str, torch.Tensor]) -> tuple[np.ndarray, np.ndarray]:
        k = s["position"].shape[0]
        body_q, body_qd = self.sim.base_state(k)
        d = {name: v.detach().cpu().double().numpy() for name, v in s.items()}
        body_q[:, self.source, :3] = d["position"]
        body_q[:, self.source, 3:] = d["orientation"][:, [1, 2, 3, 0]]
        body_qd[:, self.source, :3] = d["angular_velocity"]
        body_qd[:, self.source, 3:] = d["linear_velocity"]
        return body_q, body_qd

    def _chunks(self, k: int):
        for start in range(0, k, self.max_envs):
            yield slice(start, min(k, start + self.max_envs))

    def _records(self, losses: np.ndarray) -> np.ndarray:
        """(E,) record index whose loss counts: the last, or the best (step 0 included)."""
        if self.evaluate == "final" or self.target.time is not None:
            return np.full(losses.shape[1], losses.shape[0] - 1)
        return np.argmin(np.where(np.isfinite(losses), losses, np.inf), axis=0)

    def loss(self, x: torch.Tensor) -> torch.Tensor:
        """Losses (K,) of parameters x (K, P), without gradients."""
        self.evaluations += 1
        with torch.no_grad():
            q0, qd0 = self._initial(self._source_state(x))
        out = []
        spec = self._loss_spec()
        for sl in self._chunks(x.shape[0]):
            *_, losses, _, _ = self.sim.run(q0[sl], qd0[sl], self.steps, record_every=self.steps, loss=spec)
            values = losses.numpy()
            rec = self._records(values)
            out.append(values[rec, np.arange(values.shape[1])])
        return torch.as_tensor(np.concatenate(out), dtype=torch.float64)

    def value_and_grad(self, x: torch.Tensor, mode: str = "reverse") -> tuple[torch.Tensor, torch.Tensor]:
        """Losses (K,) and their gradients (K, P) by reverse mode through ``wp.Tape``.

        Raises:
            InferenceError: ``mode`` other than ``reverse``.
        """
        if mode != "reverse":
            raise InferenceError(f"the warp backend offers reverse-mode gradients only (wp.Tape), not {mode!r}; "
                                 f"use --gradient reverse")
        self.evaluations += 1
        x = x.detach().to(torch.float64).requires_grad_(True)
        with torch.enable_grad():
            s = self._source_state(x)
        q0, qd0 = self._initial(s)
        n = len(self.sim.bodies)
        spec = self._loss_spec()
        values, g_q, g_qd = [], [], []
        for sl in self._chunks(x.shape[0]):
            *_, losses, tape, first = self.sim.run(q0[sl], qd0[sl], self.steps, record_every=self.steps,
                                                   loss=spec, grad=True)
            v = losses.numpy()
            rec = self._records(v)
            envs = v.shape[1]
            seed = np.zeros_like(v)
            seed[rec, np.arange(envs)] = 1.0
            tape.backward(grads={losses: wp.array(seed, dtype=float, device=losses.device)})
            g_q.append(first.body_q.grad.numpy().reshape(envs, n, 7)[:, self.source].astype(np.float64))
            g_qd.append(first.body_qd.grad.numpy().reshape(envs, n, 6)[:, self.source].astype(np.float64))
            values.append(v[rec, np.arange(envs)].astype(np.float64))
            tape.zero()
            tape.reset()
        g_q, g_qd = np.concatenate(g_q), np.concatenate(g_qd)
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
        seeds = {"position": t(g_q[:, :3]), "orientation": t(g_q[:, [6, 3, 4, 5]]),
                 "angular_velocity": t(g_qd[:, :3]), "linear_velocity": t(g_qd[:, 3:])}
        with torch.enable_grad():
            total = sum((s[name] * seeds[name]).sum() for name in seeds if s[name].requires_grad)
        if isinstance(total, torch.Tensor) and total.requires_grad:
            grad = torch.autograd.grad(total, x)[0]
        else:
            grad = torch.zeros_like(x)
        return t(np.concatenate(values)), grad.detach()

    def objective_and_grad(self, x: torch.Tensor, mode: str = "reverse") -> tuple[torch.Tensor, torch.Tensor]:
        """``0.5 * loss^2`` (K,) and its gradient (K, P), as ``InferenceProblem.objective_and_grad``."""
        loss, grad = self.value_and_grad(x, mode)
        return 0.5 * loss * loss, loss.unsqueeze(-1) * grad

    def simulate(self, x: torch.Tensor, steps: int | None = None, record_every: int | None = None):
        """Rollout from parameters x (K, P): a ``Trajectory`` with states (T, K, N, ...)."""
        steps = self.steps if steps is None else int(steps)
        with torch.no_grad():
            q0, qd0 = self._initial(self._source_state(x))
        parts = [self.sim.run(q0[sl], qd0[sl], steps, record_every=record_every or self.record_every)
                 for sl in self._chunks(x.shape[0])]
        kept = parts[0][0]
        return self.sim.trajectory(kept, np.concatenate([p[1] for p in parts], 1),
                                   np.concatenate([p[2] for p in parts], 1))

    def final_pose(self, traj, index: int = 0) -> tuple[list[float], list[float]]:
        """Object-frame position (3) and orientation (4, w x y z) of the source at the last record."""
        final = traj.final
        pos = self.sim.frames.object_position(final)[index, self.source]
        return pos.tolist(), final.orientation[index, self.source].tolist()

    def trajectory_csv(self, traj, index: int = 0) -> str:
        """Trajectory CSV text of candidate ``index`` (every movable object)."""
        from dejaview.io.trajectory import trajectory_csv

        return trajectory_csv(self.sim.frames, traj, index)

    def write_trajectory(self, path, traj, index: int = 0):
        """Write the trajectory CSV of candidate ``index``; returns the path."""
        from dejaview.io.trajectory import write_trajectory_csv

        return write_trajectory_csv(path, self.sim.frames, traj, index)
