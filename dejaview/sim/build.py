"""Build a ``World`` and its initial ``State`` from a ``Scene``.

Movable objects become rigid bodies: mass properties from their mesh (or the
closed forms of their primitive) and a sphere packing (the scene's
``spheres=`` file, else one built and cached beside the mesh). Fixed objects
become static shapes: analytic signed distances for primitives, a sampled
grid (built from the mesh and cached) for meshes; a robot (``urdf``/``mjcf``)
one static shape per link collision geometry.

Backend-specific ``<simulation>`` attributes read here:
``substeps`` (int, default 2, 4 in a scene with a movable box: ``step_settings``),
``contact-frequency`` (rad/s, default ``0.25 / (dt / substeps)``, at 2 substeps where the
scene left them out), ``unload-velocity`` (m/s, default 0.01), ``sdf-spacing`` (m, default 0.01).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from dejaview.errors import GeometryError, SceneError
from dejaview.scene import bounds
from dejaview.sim.state import State
from dejaview.sim.world import (DEFAULT_MAX_PAIR_CONTACTS, DEFAULT_MAX_STATIC_CONTACTS, BodySpec,
                                StaticShape, World)

SIM_EXTRAS = {name: kind for name, (kind, _, _) in bounds.SIM_EXTRAS.items()}


def simulation_extras(scene) -> dict:
    """The backend attributes of ``<simulation>`` this simulator understands, parsed.

    Raises:
        SceneError: a value that is not a number in its range (``dejaview.scene.bounds.SIM_EXTRAS``;
            the reader refuses the same, so ``dejaview validate`` says so first). Unknown
            attributes are ignored: they may belong to another backend.
    """
    out = {}
    for key in bounds.SIM_EXTRAS:
        if key in scene.simulation.extra:
            value, reason = bounds.parse_extra(key, scene.simulation.extra[key])
            if reason:
                raise SceneError(reason, file=str(scene.path) if scene.path else None, element="simulation")
            out[key] = value
    return out


@functools.lru_cache(maxsize=32)
def _primitive_packing(shape: str, size, radius, height, max_spheres: int):
    from dejaview.geometry.packing import SpherePacking

    return SpherePacking.from_primitive(shape, size=size, radius=radius, height=height,
                                        max_spheres=max_spheres)


def _where(scene, obj) -> dict:
    return dict(file=str(scene.path) if scene.path else None, line=obj.line, element="object")


def body_from_object(scene, obj, max_spheres: int = 256) -> BodySpec:
    """Mass properties and sphere packing of one movable scene object."""
    from dejaview.geometry.mesh import load_mesh, mass_properties, primitive_mass_properties
    from dejaview.geometry.packing import SpherePacking, load_or_build_packing

    density = obj.density if obj.density is not None else 1000.0
    try:
        if obj.mesh is not None:
            mesh_path = scene.resolve(obj.mesh)
            props = mass_properties(load_mesh(mesh_path), mass=obj.mass, density=density)
            packing = load_or_build_packing(mesh_path, scene.resolve(obj.spheres),
                                            max_spheres=max_spheres)
        else:
            size = tuple(obj.size) if obj.size is not None else None
            props = primitive_mass_properties(obj.shape, size=size, radius=obj.radius,
                                              height=obj.height, mass=obj.mass, density=density)
            if obj.spheres is not None:
                packing = SpherePacking.read(scene.resolve(obj.spheres))
            else:
                packing = _primitive_packing(obj.shape, size, obj.radius, obj.height, max_spheres)
    except GeometryError as exc:
        raise SceneError(f"object {obj.id!r}: {exc}", **_where(scene, obj)) from exc
    box = obj.mesh is None and obj.shape == "box" and obj.size is not None
    return BodySpec(name=obj.id, mass=props.mass, inertia=np.asarray(props.inertia),
                    com=np.asarray(props.center_of_mass), centers=np.asarray(packing.centers),
                    radii=np.asarray(packing.radii), friction=obj.friction,
                    restitution=obj.restitution,
                    box_half=tuple(0.5 * float(v) for v in obj.size) if box else None)


def static_from_object(scene, obj, sdf_spacing: float = 0.01) -> StaticShape:
    """Static shape (analytic or grid signed distance) of one fixed scene object."""
    sim = scene.simulation
    common = dict(position=obj.pose.position, orientation=obj.pose.orientation,
                  friction=sim.friction if obj.friction is None else obj.friction,
                  restitution=sim.restitution if obj.restitution is None else obj.restitution)
    if obj.mesh is None:
        if obj.shape == "plane":
            return StaticShape.make(obj.id, "plane", **common)
        if obj.shape == "box":
            return StaticShape.make(obj.id, "box", half=0.5 * np.asarray(obj.size), **common)
        if obj.shape == "sphere":
            return StaticShape.make(obj.id, "sphere", radius=obj.radius, **common)
        return StaticShape.make(obj.id, "cylinder", radius=obj.radius, half_height=0.5 * obj.height,
                                **common)
    from dejaview.geometry.sdf import load_or_build_sdf

    try:
        grid = load_or_build_sdf(scene.resolve(obj.mesh), spacing=sdf_spacing)
    except GeometryError as exc:
        raise SceneError(f"object {obj.id!r}: {exc}", **_where(scene, obj)) from exc
    return StaticShape.make(obj.id, "grid", grid=grid.values, grid_origin=grid.origin,
                            grid_spacing=grid.spacing, **common)


def statics_from_robot(scene, obj, sdf_spacing: float = 0.01, motion: tuple[float, int] | None = None
                       ) -> list[StaticShape]:
    """Static shapes of a fixed robot object (``urdf``/``mjcf``): one per link collision geometry,
    posed by forward kinematics (``dejaview.geometry.robot``) and named ``robot-id/link``; meshes
    as signed distance grids of their solids (``RobotPiece.solid``: the convex hull of a mesh with
    holes), a uniform ``scale`` scaling the grid. A moving robot's (``<joints time values>``) shapes
    stand where they are at time 0 and carry their paths (``dejaview.sim.motion``) at the substep
    and step budget ``motion`` = (h, total substeps)."""
    from dejaview.geometry.robot import robot_pieces

    if obj.moving and motion is None:
        raise SceneError(f"robot {obj.id!r} moves: its links need the substep (motion=)", **_where(scene, obj))

    sim = scene.simulation
    material = dict(friction=sim.friction if obj.friction is None else obj.friction,
                    restitution=sim.restitution if obj.restitution is None else obj.restitution)
    statics = []
    for p in robot_pieces(scene, obj):
        common = dict(position=p.position, orientation=p.orientation, **material)
        if p.kind == "plane":
            statics.append(StaticShape.make(p.name, "plane", **common))
        elif p.kind == "box":
            statics.append(StaticShape.make(p.name, "box", half=0.5 * np.asarray(p.size), **common))
        elif p.kind == "sphere":
            statics.append(StaticShape.make(p.name, "sphere", radius=p.radius, **common))
        elif p.kind == "cylinder":
            statics.append(StaticShape.make(p.name, "cylinder", radius=p.radius, half_height=0.5 * p.height,
                                            **common))
        else:
            from dejaview.geometry.sdf import load_or_build_sdf

            try:  # the grid is built in the mesh's units at spacing / scale, then scaled
                hull = p.solid()[1]
                grid = load_or_build_sdf(p.mesh, spacing=sdf_spacing / p.scale, padding=0.1 / p.scale,
                                         convex_hull=hull)
            except GeometryError as exc:
                raise SceneError(f"object {obj.id!r}: link {p.link!r}: {exc}", **_where(scene, obj)) from exc
            statics.append(StaticShape.make(p.name, "grid", grid=p.scale * np.asarray(grid.values),
                                            grid_origin=p.scale * np.asarray(grid.origin),
                                            grid_spacing=p.scale * grid.spacing, **common))
    if obj.moving:
        from dataclasses import replace

        from dejaview.sim.motion import RobotMotion

        h, limit = motion
        paths = RobotMotion(scene, obj, limit).paths(h)
        statics = [replace(st, path=paths[st.name]).at(0) for st in statics]
    return statics


def step_settings(scene, extras: dict | None = None) -> tuple[int, float | None]:
    """Substeps per step and contact frequency (rad/s; None: ``World.build``'s default
    ``DEFAULT_OMEGA_H / h``) of a scene.

    Given substeps keep their meaning (more substeps, stiffer contacts). Left out, they are
    ``bounds.default_substeps(scene)``: 4 in a scene with a movable box, at the contact frequency
    of the default 2 substeps (``DEFAULT_OMEGA_H * 2 / dt``, 250 rad/s at dt 2 ms): the same
    stiffness, resolved twice as finely.

    Args:
        scene: a validated ``Scene``; extras: its ``simulation_extras`` (parsed here when None).
    """
    from dejaview.sim.world import DEFAULT_OMEGA_H

    extras = simulation_extras(scene) if extras is None else extras
    frequency = extras.get("contact-frequency")
    if "substeps" in extras:
        return int(extras["substeps"]), frequency
    substeps = bounds.default_substeps(scene)
    if frequency is None and substeps != bounds.DEFAULT_SUBSTEPS:
        frequency = DEFAULT_OMEGA_H * bounds.DEFAULT_SUBSTEPS / scene.simulation.dt
    return substeps, frequency


def world_from_scene(scene, *, dtype: torch.dtype = torch.float64, device=None,
                     max_spheres: int = 256, sdf_spacing: float | None = None,
                     progress=None, max_steps: int | None = None) -> World:
    """The simulator's World for a scene.

    Args:
        scene: a validated ``dejaview.scene.Scene``.
        dtype, device: of every tensor.
        max_spheres: sphere budget for packings built here.
        sdf_spacing: grid spacing of mesh signed distance fields (default from
            ``<simulation sdf-spacing>`` or 1 cm).
        progress: optional callable(str) told what is being built.
        max_steps: step budget of the scene's duration (default ``dejaview.scene.bounds.max_steps()``).
    Raises:
        SceneError: no movable object, or a geometry problem (naming the object).
        SimulationError: the duration is over the step budget, or a mass out of range.
    """
    extras = simulation_extras(scene)
    spacing = sdf_spacing or extras.get("sdf-spacing", 0.01)
    say = progress or (lambda _msg: None)
    sim = scene.simulation
    substeps, frequency = step_settings(scene, extras)
    bodies, statics = [], []
    for obj in scene.objects:
        if obj.fixed and obj.robot is not None:
            say(f"robot {obj.id}")
            statics.extend(statics_from_robot(scene, obj, spacing,
                                              motion=(sim.dt / substeps, bounds.max_steps(max_steps))))
        elif obj.fixed:
            say(f"static {obj.id}")
            statics.append(static_from_object(scene, obj, spacing))
        else:
            say(f"body {obj.id}")
            bodies.append(body_from_object(scene, obj, max_spheres))
    if not bodies:
        raise SceneError("the scene has no movable object to simulate",
                         file=str(scene.path) if scene.path else None, element="scene")
    world = World.build(bodies, statics, gravity=scene.gravity, dt=sim.dt,
                        substeps=substeps, duration=sim.duration,
                        friction=sim.friction, restitution=sim.restitution,
                        contact_frequency=frequency,
                        unload_velocity=extras.get("unload-velocity", 0.01),
                        max_static_contacts=extras.get("max-static-contacts", DEFAULT_MAX_STATIC_CONTACTS),
                        max_pair_contacts=extras.get("max-pair-contacts", DEFAULT_MAX_PAIR_CONTACTS),
                        max_steps=max_steps, dtype=dtype, device=device)
    return world


def initial_state(world: World, scene, batch_size: int = 1) -> State:
    """State of the scene's movable objects as written in the file (poses and velocities).

    Returns:
        State (batch_size, N, ...).
    """
    objs = [scene.object(name) for name in world.names]
    return world.state([o.pose.position for o in objs], [o.pose.orientation for o in objs],
                       [o.velocity.linear for o in objs], [o.velocity.angular for o in objs],
                       batch_size=batch_size)
