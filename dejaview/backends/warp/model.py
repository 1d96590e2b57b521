"""The ``warp`` backend's model: a scene as ``warp.sim`` models, and rollouts of them.

Model (``WarpSimulator.from_scene``), from the same scene as the sphere simulator:

- movable objects are bodies with DejaView's mass properties (``dejaview.geometry.mesh``: the
  same mass, centre of mass and inertia in both backends); their shapes carry no mass of their own;
- shapes: meshes as ``wp.sim.Mesh`` (vertices and faces as trimesh loads them), box and sphere as
  Warp primitives, cylinders as meshes (``warp.sim`` generates no cylinder contacts), planes as
  infinite static planes; fixed objects are static shapes (body -1), a moving robot's links
  kinematic bodies of zero mass driven along their paths (``dejaview.backends.warp.links``);
- friction and restitution per shape from the object or the scene (Warp averages the two shapes
  of a contact; the sphere simulator takes the geometric mean of the frictions), gravity, ``dt``
  and ``duration`` from the scene; the settings of ``dejaview.backends.warp.settings``.

Batches: K candidates run as K replicated environments of one Warp model (each environment's
bodies in their own collision group, the static shapes shared). ``warp.sim`` computes in float32.

Reverse mode records every step on a ``wp.Tape`` (``_Tape``, which fixes the adjoint of XPBD's
copies of its input state, locally: nothing of Warp is patched).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

import warp as wp

from dejaview.backends.warp.settings import CONTACT_MARGIN, SEMI_IMPLICIT_OMEGA_H, warp_settings
from dejaview.errors import SceneError
from dejaview.geometry.transforms import quat_multiply


def init_warp():
    """Initialise Warp and import ``warp.sim``, without its banner and notices (once).

    Warp prints its deprecation notice for ``warp.sim`` on stdout and, on machines without a
    CUDA driver, a notice on stderr; the CLI keeps both streams for results and errors.
    """
    if getattr(init_warp, "done", False):
        return
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
    init_warp.done = True


def default_device() -> str:
    """``cuda`` when Warp sees a CUDA device, else ``cpu``."""
    init_warp()
    return "cuda" if wp.is_cuda_available() else "cpu"


@wp.kernel
def _copy(src: wp.array(dtype=Any), dest: wp.array(dtype=Any)):
    i = wp.tid()
    dest[i] = src[i]


class _Tape(wp.Tape):
    """A ``wp.Tape`` on which the copies an integrator step makes of its input state accumulate
    their adjoint instead of overwriting it.

    Warp 1.9.1 records ``wp.copy`` with an adjoint that *overwrites* the source's gradient with
    the copy's. XPBD's restitution clones the input state first, so in the reverse pass the
    clone's adjoint comes last and erases every gradient reaching the input state (exactly zero
    gradients through any step with restitution). Inside ``step`` this tape records such copies
    with a kernel copy's adjoint (accumulate), keeps copies into the step's output state, and drops
    the other copies (scratch buffers that a kernel overwrites next).
    """

    def __init__(self):
        super().__init__()
        self._inputs = None
        self._outputs = None

    @contextlib.contextmanager
    def step(self, state_in, state_out):
        self._inputs = {id(state_in.body_q), id(state_in.body_qd)}
        self._outputs = {id(state_out.body_q), id(state_out.body_qd)}
        try:
            yield
        finally:
            self._inputs = self._outputs = None

    def record_func(self, backward, arrays):
        if self._inputs is None or len(arrays) != 2:
            return super().record_func(backward, arrays)
        dest, src = arrays
        if id(src) in self._inputs:
            def accumulate():
                wp.launch(_copy, dim=src.shape[0], inputs=[src], outputs=[dest], adj_inputs=[src.grad],
                          adj_outputs=[dest.grad], adjoint=True, device=dest.device)
            return super().record_func(accumulate, arrays)
        if id(dest) in self._outputs:
            return super().record_func(backward, arrays)
        return None


def _wp_quat(q) -> tuple[float, float, float, float]:
    """w x y z (scene) -> x y z w (Warp), normalised."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return (float(x), float(y), float(z), float(w))


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


def _shape_of(scene, obj, solid=None) -> tuple:
    """("mesh", (vertices, faces)) | ("box", half) | ("sphere", r) | ("plane", None); ``solid``: the
    mesh a robot link collides as (``LinkPart.solid``), instead of the file's."""
    from dejaview.geometry.mesh import load_mesh, primitive_mesh

    if obj.mesh is not None:
        mesh = solid if solid is not None else load_mesh(scene.resolve(obj.mesh))
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
    links: object = None  # a moving robot's links' rows (``links.LinkRows``), or None
    states: dict = field(default_factory=dict)  # (requires_grad, count, slot) -> list of wp.sim.State
    tapes: dict = field(default_factory=dict)  # slot -> the tape of a run whose reverse pass is to come


class WarpSimulator:
    """A scene as ``warp.sim`` models (one per batch size), and rollouts of them.

    Attributes:
        names: (N,) movable body ids; frames: their ``BodyFrames``.
        dt, duration_steps, settings (integrator, substeps, iterations), device.
    """

    def __init__(self, scene, bodies: list[_Body], statics: list[_Static], settings: dict, device: str,
                 links: list | None = None):
        self.scene = scene
        self.bodies = bodies
        self.statics = statics
        self.links = links or []  # a moving robot's link geometries (``links.MovingLink``)
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

        init_warp()
        settings = warp_settings(scene, **options)
        sim = scene.simulation
        bodies, statics, links = [], [], []
        for obj in scene.objects:
            where = dict(file=str(scene.path) if scene.path else None, line=obj.line, element="object")
            friction = sim.friction if obj.friction is None else obj.friction
            restitution = sim.restitution if obj.restitution is None else obj.restitution
            try:
                if obj.fixed and obj.robot is not None:  # a robot: one static per link geometry
                    from dejaview.scene.robot_links import link_objects

                    if obj.moving:  # kinematic bodies on their paths (``links``)
                        from dejaview.backends.warp.links import moving_links

                        links.extend(moving_links(scene, obj, sim.dt / settings["substeps"], friction,
                                                  restitution, _shape_of))
                        continue
                    statics.extend(_Static(p.object.id, _shape_of(scene, p.object, p.solid), friction,
                                           restitution, np.asarray(p.object.pose.position, dtype=np.float64),
                                           np.asarray(p.object.pose.orientation, dtype=np.float64))
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
        return cls(scene, bodies, statics, settings, device or default_device(), links)

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
        # links and statics after the bodies: warp.sim pairs a group with group -1 only when the -1
        # shape comes later; a moving link is a kinematic body of zero mass (``links``)
        static_shapes = []
        for link in self.links:
            body = builder.add_body(origin=wp.transform(wp.vec3(*link.q[0, :3]), wp.quat(*link.q[0, 3:])), m=0.0,
                                    I_m=wp.mat33(*([0.0] * 9)), com=wp.vec3(0.0, 0.0, 0.0), name=link.name)
            static_shapes.append(self._add_shape(builder, body, link.shape, wp.vec3(0.0, 0.0, 0.0),
                                                 wp.quat_identity(), dict(mu=link.friction,
                                                 restitution=link.restitution, **stiffness), -1))
        for st in self.statics:
            q = st.orientation
            if st.shape[0] == "plane":
                q = quat_multiply(q, (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0))
            static_shapes.append(self._add_shape(
                builder, -1, st.shape, wp.vec3(*st.position), wp.quat(*_wp_quat(q)),
                dict(mu=st.friction, restitution=st.restitution, **stiffness), -1))
        for a in static_shapes:  # no contacts between statics and links: nothing moves them
            for b in static_shapes:
                if a < b:
                    builder.shape_collision_filter_pairs.add((a, b))
        model = builder.finalize(device=self.device, requires_grad=True)
        model.ground = False
        model.gravity = self.gravity
        rows = None
        if self.links:
            from dejaview.backends.warp.links import LinkRows

            rows = LinkRows(self.links, self.device)
        if self.settings["integrator"] == "xpbd":
            # (warp.sim's restitution pass fails on a model that can have no contact at all)
            integrator = wp.sim.XPBDIntegrator(
                iterations=self.settings["iterations"],
                enable_restitution=self.settings["restitution"] and model.rigid_contact_max > 0)
        else:
            integrator = wp.sim.SemiImplicitIntegrator(angular_damping=0.0, friction_smoothing=0.01)
        return _Batch(model, integrator, envs, rows)

    def batch(self, envs: int) -> _Batch:
        """The model of ``envs`` environments (built once per size)."""
        if envs not in self._batches:
            self._batches[envs] = self._build(envs)
        return self._batches[envs]

    def _states(self, batch: _Batch, count: int, grad: bool, slot: int) -> list:
        key = (grad, count, slot)
        if key not in batch.states:  # one list per mode and slot
            batch.states = {k: v for k, v in batch.states.items() if (k[0], k[2]) != (grad, slot)}
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
            grad: bool = False, slot: int = 0):
        """Simulate a chunk of environments.

        Args:
            body_q: (E, N, 7) initial origins and x y z w quaternions.
            body_qd: (E, N, 6) initial angular and linear (centre-of-mass) velocities, world frame.
            steps: number of steps of ``dt``.
            record_every: keep every k-th state (the first and the last always).
            grad: record on a ``wp.Tape`` for a reverse pass (``WarpRun.backward``).
            slot: which set of state buffers to use: runs whose reverse pass is still to come
                need one each.
        Returns:
            WarpRun: record steps, body_q records (T, E, N, 7) and body_qd records (T, E, N, 6) as
            float64 torch tensors, and what a reverse pass needs.
        """
        envs = body_q.shape[0]
        batch = self.batch(envs)
        model, integrator = batch.model, batch.integrator
        sub = self.settings["substeps"]
        h = self.substep
        states = self._states(batch, steps * sub + 1, grad, slot)
        pending = batch.tapes.pop(slot, None) if grad else None
        if pending is not None:  # a run whose reverse pass never came: clear its gradients
            pending.zero()
            pending.reset()
        n = len(self.bodies)
        rows, m = batch.links, envs * n  # a moving robot's links: bodies m on
        q0, qd0 = body_q.reshape(m, 7), body_qd.reshape(m, 6)
        if rows is not None:
            q0 = np.concatenate([q0, np.zeros((rows.count, 7))])
            qd0 = np.concatenate([qd0, np.zeros((rows.count, 6))])
        states[0].body_q.assign(wp.array(q0.astype(np.float32), dtype=wp.transform, device=self.device))
        states[0].body_qd.assign(wp.array(qd0.astype(np.float32), dtype=wp.spatial_vector, device=self.device))
        tape = _Tape() if grad else None
        kept, qs, qds, recorded = [], [], [], []

        def record(t):
            if t % record_every == 0 or t == steps:
                # now: without a tape, XPBD uses its input state as scratch space
                state = states[t * sub]
                kept.append(t)
                recorded.append(state)
                qs.append(wp.to_torch(state.body_q)[:m].reshape(envs, n, 7).to(torch.float64))
                qds.append(wp.to_torch(state.body_qd)[:m].reshape(envs, n, 6).to(torch.float64))

        with tape if grad else contextlib.nullcontext():
            record(0)
            for t in range(steps):
                if rows is not None:
                    rows.write(states[t * sub], t * sub, m)
                wp.sim.collide(model, states[t * sub], requires_grad=grad)
                for s in range(sub):
                    i = t * sub + s
                    if rows is not None and s:
                        rows.write(states[i], i, m)
                    states[i].clear_forces()
                    with tape.step(states[i], states[i + 1]) if grad else contextlib.nullcontext():
                        integrator.simulate(model, states[i], states[i + 1], h)
                record(t + 1)
        if grad:
            batch.tapes[slot] = tape
        return WarpRun(kept, torch.stack(qs).cpu(), torch.stack(qds).cpu(), tape, recorded, batch, slot)

    def trajectory(self, kept, qs: torch.Tensor, qds: torch.Tensor):
        """A ``Trajectory`` (states (T, E, N, ...), centres of mass, w x y z) of ``run``'s records
        (float64 torch tensors; differentiable where they are)."""
        from dejaview.sim.rotation import quat_rotate
        from dejaview.sim.state import State, Trajectory

        q = qs[..., [6, 3, 4, 5]]
        q = q / q.norm(dim=-1, keepdim=True)
        origin = qs[..., :3]
        com = origin + quat_rotate(q, self.frames.com.expand_as(origin))
        state = State(com, q, qds[..., 3:], qds[..., :3])
        return Trajectory(state, torch.tensor(kept), self.dt)


@dataclass
class WarpRun:
    """What ``WarpSimulator.run`` recorded, and its reverse pass.

    Attributes:
        kept: record steps (T,); body_q: (T, E, N, 7) and body_qd: (T, E, N, 6), float64.
        tape: the ``wp.Tape`` (None without gradients); recorded: the recorded ``wp.sim.State``s.
    """

    kept: list
    body_q: torch.Tensor
    body_qd: torch.Tensor
    tape: Any
    recorded: list
    batch: Any
    slot: int

    def backward(self, g_q: torch.Tensor, g_qd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Gradients (E, N, 7), (E, N, 6) of the initial body_q, body_qd from those of the records."""
        envs, n = g_q.shape[1], g_q.shape[2]
        m = envs * n  # the bodies' rows (a moving robot's links come after them)
        for t, state in enumerate(self.recorded):
            wp.to_torch(state.body_q.grad)[:m].add_(g_q[t].reshape(-1, 7).to(torch.float32))
            wp.to_torch(state.body_qd.grad)[:m].add_(g_qd[t].reshape(-1, 6).to(torch.float32))
        self.tape.backward()
        first = self.recorded[0]
        gq = wp.to_torch(first.body_q.grad)[:m].reshape(envs, n, 7).to(torch.float64).cpu()
        gqd = wp.to_torch(first.body_qd.grad)[:m].reshape(envs, n, 6).to(torch.float64).cpu()
        self.tape.zero()
        self.tape.reset()
        if self.batch.tapes.get(self.slot) is self.tape:
            del self.batch.tapes[self.slot]
        return gq, gqd


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
        ``dejaview.sim.trajectory_csv.write_trajectory_csv(path, frames, trajectory)``.
    """
    from dejaview.scene import Scene

    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    sim = WarpSimulator.from_scene(scene, device=device, **options)
    q, qd = sim.base_state(1)
    run = sim.run(q, qd, sim.duration_steps if steps is None else int(steps), record_every=record_every)
    return sim.frames, sim.trajectory(run.kept, run.body_q, run.body_qd)
