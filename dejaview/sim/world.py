"""The static part of a simulation: bodies, sphere packings, static geometry, contact settings.

A ``World`` is built once (``World.from_scene`` or ``World.build``) and never
changes; ``step(world, state)`` reads it. Movable bodies are listed in scene
order; their sphere packings are stored padded to a common count ``S`` with a
mask, centred on each body's centre of mass.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields, replace

import numpy as np
import torch

from dejaview.errors import SimulationError
from dejaview.geometry.transforms import quat_to_matrix
from dejaview.scene import bounds
from dejaview.sim import sdf as _sdf
from dejaview.sim.box_edges import static_edge_points
from dejaview.sim.restitution import UNLOAD_MIN, loading_of
from dejaview.sim.rotation import quat_rotate, small_matmul
from dejaview.sim.state import State

STATIC_KINDS = ("plane", "box", "sphere", "cylinder", "grid")

# Default contact stiffness: omega_0 h = 0.25, so an impact (pi / omega_0) spans ~12
# substeps. Stiffer (0.5) halves impact penetration but resolves impact friction
# worse: a tumbling box then rests 2.7 cm from MuJoCo's answer instead of 1.3 cm
# (tests/sim/test_mujoco_crosscheck.py). More substeps buy stiffness back.
DEFAULT_OMEGA_H = 0.25


def _tensor_fields_to(obj, device=None, dtype=None):
    changes = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, torch.Tensor):
            changes[f.name] = v.to(device=device, dtype=dtype if v.is_floating_point() else None)
    return replace(obj, **changes)


@dataclass(frozen=True)
class StaticShape:
    """A fixed piece of geometry queried through its signed distance.

    Attributes:
        name: object id.
        kind: one of ``STATIC_KINDS``.
        rotation: (3, 3) world-from-shape rotation.
        translation: (3,) shape origin in the world.
        half: (3,) box half extents (zeros otherwise).
        radius: sphere / cylinder radius (0 otherwise).
        half_height: cylinder half height (0 otherwise).
        grid: (nx, ny, nz) sampled distances for ``kind == "grid"`` (else a 1-element dummy).
        grid_origin: (3,) grid node (0, 0, 0) in the shape frame.
        grid_spacing: grid node spacing.
        friction, restitution: material of this shape.
        edge_points: a box's (E, 3) points along its edges in the world (``box_edges``), made
            with it; None for the other kinds.
        path: where the shape moves (a moving robot's link, ``dejaview.sim.motion.ShapePath``);
            None for a shape that stands. Its pose above is the path's start; ``at`` poses it.
        velocity, angular_velocity: (3,) a posed moving shape's velocity at its origin and its
            angular velocity (``at``); None for a shape that stands.
    """

    name: str
    kind: str
    rotation: torch.Tensor
    translation: torch.Tensor
    friction: float
    restitution: float
    half: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    radius: float = 0.0
    half_height: float = 0.0
    grid: torch.Tensor = field(default_factory=lambda: torch.zeros(1, 1, 1, dtype=torch.float64))
    grid_origin: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    grid_spacing: float = 1.0
    edge_points: torch.Tensor | None = field(default=None, repr=False, compare=False)
    path: object = field(default=None, repr=False, compare=False)
    velocity: torch.Tensor | None = field(default=None, repr=False, compare=False)
    angular_velocity: torch.Tensor | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self.kind == "box" and self.edge_points is None:  # made once, outside any compiled code
            object.__setattr__(self, "edge_points", static_edge_points(self))

    @staticmethod
    def make(name: str, kind: str, position=(0, 0, 0), orientation=(1, 0, 0, 0), friction=0.5,
             restitution=0.2, **params) -> "StaticShape":
        """Build a static shape from plain numbers (float64 tensors).

        ``params``: ``half`` (box), ``radius`` (sphere, cylinder), ``half_height``
        (cylinder), ``grid``/``grid_origin``/``grid_spacing`` (grid).
        """
        if kind not in STATIC_KINDS:
            raise SimulationError(f"unknown static shape kind {kind!r}")
        t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
        kw = {}
        for key in ("half", "grid", "grid_origin"):
            if key in params:
                kw[key] = t(params[key])
        for key in ("radius", "half_height", "grid_spacing"):
            if key in params:
                kw[key] = float(params[key])
        return StaticShape(name=name, kind=kind, rotation=t(quat_to_matrix(orientation)),
                           translation=t(position), friction=float(friction),
                           restitution=float(restitution), **kw)

    def to(self, device=None, dtype=None) -> "StaticShape":
        moved = _tensor_fields_to(self, device, dtype)
        return moved if self.path is None else replace(moved, path=self.path.to(device, dtype))

    def at(self, substep: int) -> "StaticShape":
        """This moving shape where its path puts it at substep number ``substep`` (the path's last
        row after its end), with that row's velocities; a shape that stands is itself."""
        p = self.path
        if p is None:
            return self
        j = p.row(substep)
        rot, trans = p.rotation[j], p.translation[j]
        edges = None
        if self.edge_points is not None:  # the same points, carried along: R_j R_0^T (e - t_0) + t_j
            edges = small_matmul(small_matmul(self.edge_points - self.translation, self.rotation), rot.T) + trans
        return replace(self, rotation=rot, translation=trans, edge_points=edges, velocity=p.velocity[j],
                       angular_velocity=p.angular_velocity[j])

    def distance(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance and outward normal at world points.

        Args:
            points: (..., 3) world positions.
        Returns:
            distance (...), unit-ish normal (..., 3) in the world frame.
        """
        local = small_matmul(points - self.translation, self.rotation)  # R^T (p - t)
        if self.kind == "plane":
            d, n = _sdf.sdf_plane(local)
        elif self.kind == "box":
            d, n = _sdf.sdf_box(local, self.half)
        elif self.kind == "sphere":
            d, n = _sdf.sdf_sphere(local, self.radius)
        elif self.kind == "cylinder":
            d, n = _sdf.sdf_cylinder(local, self.radius, self.half_height)
        else:
            d, n = _sdf.sdf_grid(local, self.grid, self.grid_origin, self.grid_spacing)
        return d, small_matmul(n, self.rotation.T)


@dataclass(frozen=True)
class BodySpec:
    """Plain-number description of one movable body, input of ``World.build``.

    Attributes:
        name: object id.
        mass: kg.
        inertia: (3, 3) inertia tensor about the centre of mass, object axes.
        com: (3,) centre of mass in the object frame.
        centers: (S, 3) sphere centres in the object frame.
        radii: (S,) sphere radii.
        friction, restitution: material (None: the scene's).
        box_half: (3,) half extents where the body is a box centred on its centre of mass along its
            body axes (a primitive box): other bodies' spheres meet its exact faces, edges and
            corners (``dejaview.sim.contacts``, "Body pairs against a box"); None otherwise.
    """

    name: str
    mass: float
    inertia: np.ndarray
    com: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    friction: float | None = None
    restitution: float | None = None
    box_half: tuple | None = None


DEFAULT_MAX_STATIC_CONTACTS = 64
DEFAULT_MAX_PAIR_CONTACTS = 64


@dataclass(frozen=True)
class ContactSettings:
    """Numbers of the contact model (see ``dejaview.sim.contacts``).

    Attributes:
        frequency: body-level contact natural frequency omega_0 (rad/s).
        unload_velocity: speed over which a contact blends from loading to unloading stiffness (m/s).
        max_static_contacts: per body and static shape, the deepest this many spheres
            are computed as contacts (``dejaview.sim.contacts``).
        max_pair_contacts: per body pair, the deepest this many sphere pairs.
    """

    frequency: float
    unload_velocity: float = 0.01
    max_static_contacts: int = DEFAULT_MAX_STATIC_CONTACTS
    max_pair_contacts: int = DEFAULT_MAX_PAIR_CONTACTS


RESTITUTION_PHASES = 16
"""Onsets of an impact within its substep that ``_discrete_restitution`` averages over."""


def _discrete_restitution(unload: float, omega_h: float) -> float:
    """Restitution of one hysteretic spring contact under the simulator's integrator.

    Unit mass, omega = 1, step ``omega_h``, approach speed 1, no gravity, no v_s (its m/s are
    nothing beside an impact's): semi-implicit Euler of ``a = delta (phi + (1 - phi) s)`` with
    ``dejaview.sim.restitution.loading_of``'s blend s, until separation; the separation speed averaged
    over ``RESTITUTION_PHASES`` onsets of the contact within its first substep (the blend leaves a
    few thousandths between them, where the deepest point falls). A factor below zero is cut off
    where it crosses zero (``contacts.normal_force``).
    """
    total = 0.0
    for k in range(RESTITUTION_PHASES):
        x, v = omega_h * k / RESTITUTION_PHASES, -1.0
        out = 0.0
        for _ in range(100000):
            depth = max(0.0, -x)
            if depth > 0.0:
                s = loading_of(depth, v, 0.0, 1.0)
                a = depth * max(0.0, unload + (1.0 - unload) * s)
            else:
                a = 0.0
            v += omega_h * a
            x += omega_h * v
            if x >= 0.0 and v > 0.0:
                out = v
                break
        total += out
    return total / RESTITUTION_PHASES


@functools.lru_cache(maxsize=256)
def restitution_to_unloading(e: float, omega_h: float = DEFAULT_OMEGA_H) -> float:
    """Unloading stiffness factor phi that gives restitution ``e`` in simulation.

    A contact is stiffer when loading (k) than when unloading (phi k), so it
    gives back phi of the stored energy: in continuous time phi = e^2. The
    value is corrected by bisection on the discrete contact integrated with
    substep ``omega_h = omega_0 h`` so the simulated restitution of a head-on
    impact is ``e``. Monotone in ``e``. Below the restitution phi = 0 gives (0.111
    at omega_h 0.25: the blend's own, ``dejaview.sim.restitution``) phi is negative, down to
    ``UNLOAD_MIN``, which every ``e`` at or below its restitution (0.045) gets.
    """
    if e <= 0.0:
        return UNLOAD_MIN
    at_zero = _discrete_restitution(0.0, omega_h)
    if at_zero < e:  # above the blend's own restitution: phi in [0, 1], as before UNLOAD_MIN
        lo, hi = 0.0, 1.0
        if _discrete_restitution(hi, omega_h) <= e:
            return hi
    else:
        lo, hi = UNLOAD_MIN, 0.0
        if at_zero <= e:
            return hi
        if _discrete_restitution(lo, omega_h) >= e:
            return lo
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if _discrete_restitution(mid, omega_h) < e:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def remap_unloading(phi: torch.Tensor, omega_h0: float, omega_h: float,
                    restitution_factor: float = 1.0) -> torch.Tensor:
    """Unloading factors ``phi`` (any shape) mapped from substep ``omega_h0`` to ``omega_h``: each
    pair's simulated restitution recovered at ``omega_h0``, times ``restitution_factor``, clipped
    to [0, 1], and the factor that gives it at ``omega_h`` (a pair at the least factor stays there)."""
    flat = [restitution_to_unloading(min(1.0, max(0.0, _discrete_restitution(float(p), omega_h0)
                                                  * restitution_factor)), omega_h)
            if float(p) > UNLOAD_MIN else UNLOAD_MIN for p in phi.reshape(-1).tolist()]
    return torch.tensor(flat, dtype=phi.dtype, device=phi.device).reshape(phi.shape)


@dataclass(frozen=True)
class World:
    """Static description of a scene for the sphere-packing simulator.

    Attributes (N movable bodies, S spheres per body after padding, K static shapes):
        names: (N,) body ids.
        mass: (N,) kg.
        inertia: (N, 3, 3) body-frame inertia about the centre of mass.
        inv_inertia: (N, 3, 3) its inverse.
        com: (N, 3) centre of mass in the object frame.
        centers: (N, S, 3) sphere centres relative to the centre of mass, body axes.
        radii: (N, S) sphere radii (0 for padding).
        mask: (N, S) 1 for real spheres, 0 for padding.
        bound: (N,) radius of a sphere about the centre of mass holding all spheres (a box's: and its corners).
        inv_inertia_min: (N,) 1 / smallest principal moment (for contacts' effective masses).
        statics: K static shapes.
        mu_static: (N, K) friction coefficient body vs static.
        unload_static: (N, K) unloading stiffness factor body vs static (restitution).
        pairs: (P, 2) movable body pairs checked for contact.
        mu_pair, unload_pair, mass_pair: (P,) friction, unloading factor, reduced mass per pair.
        box_half: (N, 3) half extents of the bodies that are boxes (``BodySpec.box_half``), 0 for
            the others.
        pair_surface: (P,) per body pair, which body's exact box surface the other's spheres meet:
            0 (a's), 1 (b's), or -1 (sphere against sphere: neither or both are boxes).
        box_bodies: (N,) whether each body is a box (plain booleans: the static box edges'
            ``dejaview.sim.box_edges`` branch on them, also under ``torch.compile``).
        gravity: (3,) m/s^2.
        dt: step (s); substeps: integration substeps per step; steps: default rollout length.
        contact: contact model numbers.
        physics: (B, 3) or None: one physics per candidate of a batch, the logs of factors on
            every pair's friction, unloading factor (capped at 1) and the contact stiffness
            (``dejaview.sim.physics``; ``integrate.rollout``'s ``physics`` sets it).
    """

    names: tuple[str, ...]
    mass: torch.Tensor
    inertia: torch.Tensor
    inv_inertia: torch.Tensor
    com: torch.Tensor
    centers: torch.Tensor
    radii: torch.Tensor
    mask: torch.Tensor
    bound: torch.Tensor
    inv_inertia_min: torch.Tensor
    statics: tuple[StaticShape, ...]
    mu_static: torch.Tensor
    unload_static: torch.Tensor
    pairs: torch.Tensor
    mu_pair: torch.Tensor
    unload_pair: torch.Tensor
    mass_pair: torch.Tensor
    box_half: torch.Tensor
    pair_surface: tuple
    box_bodies: tuple
    gravity: torch.Tensor
    dt: float
    substeps: int
    steps: int
    contact: ContactSettings
    physics: torch.Tensor | None = None

    # ---------------------------------------------------------------- build
    @staticmethod
    def build(bodies: list[BodySpec], statics: list[StaticShape], *, gravity=(0.0, 0.0, -9.81),
              dt: float = 0.002, substeps: int = 2, steps: int | None = None,
              duration: float | None = None, friction: float = 0.5, restitution: float = 0.2,
              contact_frequency: float | None = None, unload_velocity: float = 0.01,
              max_static_contacts: int = DEFAULT_MAX_STATIC_CONTACTS,
              max_pair_contacts: int = DEFAULT_MAX_PAIR_CONTACTS, max_steps: int | None = None,
              dtype: torch.dtype = torch.float64, device=None) -> "World":
        """Assemble a world from body and static descriptions.

        Args:
            bodies: movable bodies (at least one).
            statics: fixed shapes.
            dt: step length; substeps: integration substeps per step.
            steps / duration: default rollout length (steps wins).
            friction, restitution: defaults for bodies and shapes without their own.
            contact_frequency: omega_0 in rad/s (default ``DEFAULT_OMEGA_H / (dt / substeps)``).
            unload_velocity: speed over which contacts blend loading/unloading stiffness (m/s).
            max_static_contacts, max_pair_contacts: contact capacity (see ``ContactSettings``).
            max_steps: budget of the default rollout, steps x substeps (default ``bounds.max_steps()``).
        Raises:
            SimulationError: settings out of range (``dejaview.scene.bounds``), a default rollout over
                the step budget, a body without spheres or with a bad mass or inertia.
        """
        if not bodies:
            raise SimulationError("a world needs at least one movable body")
        if not (dt > 0 and math.isfinite(dt)) or not 1 <= substeps <= bounds.MAX_SUBSTEPS:
            raise SimulationError(f"invalid time step dt={dt} substeps={substeps} (substeps 1.."
                                  f"{bounds.MAX_SUBSTEPS})")
        if not 1 <= min(max_static_contacts, max_pair_contacts) <= max(max_static_contacts,
                                                                     max_pair_contacts) <= bounds.MAX_CONTACTS:
            raise SimulationError(f"contact capacities must be 1..{bounds.MAX_CONTACTS}, got "
                                  f"{max_static_contacts} (static) and {max_pair_contacts} (pair)")
        g = [float(c) for c in gravity]
        if not all(math.isfinite(c) for c in g) or math.hypot(*g) > bounds.MAX_GRAVITY:
            raise SimulationError(f"gravity {tuple(g)} is beyond the limit of {bounds.MAX_GRAVITY:g} m/s^2")
        if steps is None:
            count = bounds.step_count(duration if duration is not None else 1.5, dt)
        else:
            count = float(steps)
        reason = bounds.budget_problem(count, substeps, bounds.max_steps(max_steps), "the default rollout")
        if reason:
            raise SimulationError(reason)
        steps = int(count)
        n = len(bodies)
        s_max = max(len(b.radii) for b in bodies)
        centers = np.zeros((n, s_max, 3))
        radii = np.zeros((n, s_max))
        mask = np.zeros((n, s_max))
        inertia = np.zeros((n, 3, 3))
        com = np.zeros((n, 3))
        bound = np.zeros(n)
        inv_i_min = np.zeros(n)
        mass = np.zeros(n)
        box_half = np.zeros((n, 3))
        for i, b in enumerate(bodies):
            if not (bounds.MIN_MASS <= b.mass <= bounds.MAX_MASS):
                raise SimulationError(f"body {b.name!r}: mass {b.mass:.4g} kg is outside "
                                      f"{bounds.MIN_MASS:g}..{bounds.MAX_MASS:g} kg")
            if len(b.radii) == 0:
                raise SimulationError(f"body {b.name!r}: no spheres")
            s = len(b.radii)
            c = np.asarray(b.centers, dtype=np.float64) - np.asarray(b.com, dtype=np.float64)
            centers[i, :s] = c
            radii[i, :s] = b.radii
            mask[i, :s] = 1.0
            inertia[i] = b.inertia
            com[i] = b.com
            mass[i] = b.mass
            bound[i] = float(np.max(np.linalg.norm(c, axis=1) + np.asarray(b.radii)))
            if b.box_half is not None:
                half = np.asarray(b.box_half, dtype=np.float64).reshape(3)
                if not (np.all(np.isfinite(half)) and np.all(half > 0)):
                    raise SimulationError(f"body {b.name!r}: box half extents {tuple(half)} must be positive")
                box_half[i] = half
                bound[i] = max(bound[i], float(np.linalg.norm(half)))  # the corners, not the spheres'
            i_min = float(np.linalg.eigvalsh(inertia[i]).min())
            if not i_min > 0:
                raise SimulationError(f"body {b.name!r}: inertia is not positive definite")
            inv_i_min[i] = 1.0 / i_min
        mus = np.array([friction if b.friction is None else b.friction for b in bodies])
        es = np.array([restitution if b.restitution is None else b.restitution for b in bodies])
        h = dt / substeps
        omega = float(contact_frequency or DEFAULT_OMEGA_H / h)
        if not (omega > 0 and omega * h <= bounds.MAX_CONTACT_OMEGA_H):
            raise SimulationError(f"contact frequency {omega:.4g} rad/s is unstable with substeps of {h:.4g} s "
                                  f"(frequency x substep must be in (0, {bounds.MAX_CONTACT_OMEGA_H:g}])")
        unload = functools.partial(restitution_to_unloading, omega_h=omega * h)
        k = len(statics)
        mu_static = np.zeros((n, k))
        unload_static = np.zeros((n, k))
        for j, st in enumerate(statics):
            mu_static[:, j] = np.sqrt(mus * st.friction)
            unload_static[:, j] = [unload(0.5 * (e + st.restitution)) for e in es]
        pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]
        mu_pair = np.array([math.sqrt(mus[a] * mus[b]) for a, b in pairs])
        unload_pair = np.array([unload(0.5 * (es[a] + es[b])) for a, b in pairs])
        mass_pair = np.array([mass[a] * mass[b] / (mass[a] + mass[b]) for a, b in pairs])
        is_box = [bool(np.any(box_half[i] > 0)) for i in range(n)]
        pair_surface = tuple(-1 if is_box[a] == is_box[b] else (0 if is_box[a] else 1) for a, b in pairs)
        f = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
        world = World(
            names=tuple(b.name for b in bodies), mass=f(mass), inertia=f(inertia),
            inv_inertia=f(np.linalg.inv(inertia)), com=f(com), centers=f(centers), radii=f(radii),
            mask=f(mask), bound=f(bound), inv_inertia_min=f(inv_i_min), statics=tuple(statics),
            mu_static=f(mu_static), unload_static=f(unload_static),
            pairs=torch.as_tensor(np.asarray(pairs, dtype=np.int64).reshape(-1, 2)),
            mu_pair=f(mu_pair), unload_pair=f(unload_pair), mass_pair=f(mass_pair),
            box_half=f(box_half), pair_surface=pair_surface, box_bodies=tuple(is_box), gravity=f(gravity),
            dt=float(dt), substeps=int(substeps),
            steps=int(steps),
            contact=ContactSettings(frequency=omega,
                                    unload_velocity=float(unload_velocity),
                                    max_static_contacts=int(max_static_contacts),
                                    max_pair_contacts=int(max_pair_contacts)))
        return world.to(device=device, dtype=dtype)

    @staticmethod
    def from_scene(scene, *, dtype: torch.dtype = torch.float64, device=None,
                   max_spheres: int = 256, sdf_spacing: float | None = None, progress=None,
                   max_steps: int | None = None) -> "World":
        """Build the world of a ``dejaview.scene.Scene`` (see ``dejaview.sim.build``; ``sdf_spacing``
        default: the scene's ``<simulation sdf-spacing>``, else 1 cm)."""
        from dejaview.sim.build import world_from_scene

        return world_from_scene(scene, dtype=dtype, device=device, max_spheres=max_spheres,
                                sdf_spacing=sdf_spacing, progress=progress, max_steps=max_steps)

    def with_substeps(self, substeps: int) -> "World":
        """This world integrated in ``substeps`` substeps per step at the same contact frequency
        (stiffness), each unloading factor re-mapped so that it rebounds with the same restitution:
        the same model at a finer (or coarser) step, to measure the step's share of a result. A moving
        robot's links are sampled again at the new substep (``ShapePath.motion``: a path built
        without one, by hand, is refused)."""
        om = self.contact.frequency
        h0, h = self.dt / self.substeps, self.dt / substeps
        statics = self.statics
        if self.moving and substeps != self.substeps:
            from dejaview.sim.motion import resampled

            statics = resampled(statics, h)
        return replace(self, substeps=int(substeps), statics=statics,
                       unload_static=remap_unloading(self.unload_static, om * h0, om * h),
                       unload_pair=remap_unloading(self.unload_pair, om * h0, om * h))

    def to(self, device=None, dtype=None) -> "World":
        """Move every tensor (statics included) to ``device`` / floating ``dtype``."""
        w = _tensor_fields_to(self, device, dtype)
        return replace(w, statics=tuple(s.to(device, dtype) for s in self.statics))

    # -------------------------------------------------------------- queries
    @property
    def moving(self) -> bool:
        """Whether some static shape moves (a moving robot's links, ``dejaview.sim.motion``)."""
        return any(s.path is not None for s in self.statics)

    def posed(self, substep: int) -> "World":
        """This world with its moving statics where they are at substep number ``substep`` of a
        rollout from time 0 (``StaticShape.at``); a world without any is itself."""
        if not self.moving:
            return self
        return replace(self, statics=tuple(s.at(substep) for s in self.statics))

    @property
    def num_bodies(self) -> int:
        return len(self.names)

    @property
    def dtype(self) -> torch.dtype:
        return self.mass.dtype

    @property
    def device(self) -> torch.device:
        return self.mass.device

    def body_index(self, name: str) -> int:
        """Index of the movable body called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise SimulationError(f"no movable body {name!r} (movable: {', '.join(self.names)})") from None

    def state(self, position, orientation=None, linear_velocity=None, angular_velocity=None,
              batch_size: int | None = None) -> State:
        """State from object-frame poses (as in a scene file) and velocities.

        Args:
            position: (B, N, 3) or (N, 3) object-frame origins.
            orientation: (B, N, 4) or (N, 4) quaternions (normalised here); default identity.
            linear_velocity, angular_velocity: (B, N, 3) or (N, 3); default zero.
            batch_size: repeat unbatched inputs this many times (default 1).
        Returns:
            State with centre-of-mass positions.
        """
        n = self.num_bodies
        kw = dict(dtype=self.dtype, device=self.device)

        def prep(x, default):
            x = torch.as_tensor(default if x is None else x, **kw)
            if x.dim() == 2:
                x = x.unsqueeze(0)
            if x.shape[1] != n:
                raise SimulationError(f"expected {n} bodies in the state, got shape {tuple(x.shape)}")
            return x

        pos = prep(position, None if position is not None else [[0.0] * 3] * n)
        q = prep(orientation, [[1.0, 0.0, 0.0, 0.0]] * n)
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        v = prep(linear_velocity, [[0.0] * 3] * n)
        w = prep(angular_velocity, [[0.0] * 3] * n)
        b = max(pos.shape[0], q.shape[0], v.shape[0], w.shape[0], batch_size or 1)
        pos, q, v, w = (t.expand(b, *t.shape[1:]) for t in (pos, q, v, w))
        return State(pos + quat_rotate(q, self.com.expand_as(pos)), q, v, w)

    def object_position(self, state: State) -> torch.Tensor:
        """Object-frame origins of all bodies: (B, N, 3) (the COM minus the rotated offset)."""
        return state.position - quat_rotate(state.orientation, self.com.expand_as(state.position))

    def sphere_positions(self, state: State) -> torch.Tensor:
        """World positions of every sphere centre: (B, N, S, 3)."""
        from dejaview.sim.rotation import quat_to_matrix

        rot = quat_to_matrix(state.orientation)  # (B, N, 3, 3)
        return state.position.unsqueeze(-2) + self.centers @ rot.transpose(-1, -2)
