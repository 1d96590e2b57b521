"""PyBullet as a second observing engine: a DejaView scene simulated in Bullet, its material mapped fairly.

``bullet_run(scene, times, state)`` is ``crossengine_engines.mujoco_run``'s twin: the object-frame
origins and orientations of every movable object at ``times``. Planes, boxes, spheres and
cylinders (axis z in both engines) only: the cases' shapes. The mapping
(docs/physics-fidelity.md, "Mapping DejaView's contact onto Bullet"):

* Friction: Bullet combines a contact pair's coefficients by their product, DejaView by the
  geometric mean; each body gets ``sqrt(mu)``, so a pair's product is DejaView's
  ``sqrt(mu_a mu_b)`` for any two materials.
* Restitution: Bullet's product again; each body gets ``sqrt(e)``: a pair's ``sqrt(e_a e_b)``
  is DejaView's mean ``(e_a + e_b) / 2`` where the two agree (every case of the bench), and
  their geometric mean where they do not.
* Damping: Bullet damps every body by default (``linearDamping`` and ``angularDamping``
  0.04); DejaView does not: 0.
* Contact: Bullet's own rigid contact (impulses, no stiffness to map), without rolling or
  spinning friction (DejaView has neither), at ``BULLET_TIMESTEP``, contacts where bodies touch (``CONTACT``), with
  ``SOLVER_ITERATIONS`` sequential-impulse iterations. Bullet only applies restitution above
  a closing speed (``restitutionVelocityThreshold``, 0.2 m/s by default): ``RESTITUTION_THRESHOLD``.
* Mass: DejaView's mass and diagonal inertia (uniform density) of each primitive, centred
  at the object's origin, so both engines move the same body.
"""

from __future__ import annotations

import math

import numpy as np

BULLET_TIMESTEP = 2.5e-4
"""Seconds: Bullet's step here (docs/physics-fidelity.md, "Bullet's time step": converged)."""
SOLVER_ITERATIONS = 100
RESTITUTION_THRESHOLD = 0.01
"""m/s: closing speeds below this rebound with restitution 0 in Bullet (its default 0.2 m/s
would make a ball dropped 2 mm stick where DejaView's bounces)."""
CONTACT = {"contactBreakingThreshold": 1e-5, "contactERP": 0.01}
"""Bullet's contacts made within 10 um of a touch, not 2 cm (its default; a global of Bullet's, so
set on every run): Bullet gives a contact restitution only in its first frames, and a contact made
2 cm ahead at a small step has aged out before the touch (a ball dropped 0.5 m with e 0.5 did
not bounce at a 0.25 ms step; at 0.5 mm ahead the bounces still moved 4-5 cm between steps). A
weak push-out of penetration (``contactERP`` 0.01, Bullet's 0.2): the push-out's velocity adds
to a rebound (e 0.3 bounced 58 % above e^2 h at 0.2, 2 % at 0.01), and without any a box
resting on the floor sank 1.3-1.4 mm in a second (docs/physics-fidelity.md, "Bullet")."""
SHAPES = ("plane", "box", "sphere", "cylinder")


def material(friction: float, restitution: float) -> dict:
    """One body's Bullet dynamics for DejaView's ``friction`` and ``restitution``: the square
    roots, so that Bullet's product over a pair gives DejaView's combined value (module docstring).

    Raises:
        ValueError: a negative friction or a restitution outside [0, 1].
    """
    if not (friction >= 0 and 0 <= restitution <= 1):
        raise ValueError(f"Bullet material: friction {friction!r} must be >= 0, restitution {restitution!r} "
                         "in [0, 1]")
    return {"lateralFriction": math.sqrt(friction), "restitution": math.sqrt(restitution),
            "rollingFriction": 0.0, "spinningFriction": 0.0, "linearDamping": 0.0, "angularDamping": 0.0}


def _xyzw(q) -> list:
    w, x, y, z = (float(v) for v in q)
    return [x, y, z, w]


def _shape(bullet, client: int, obj) -> int:
    kind = obj.geometry_kind
    if kind not in SHAPES:
        raise ValueError(f"Bullet: object {obj.id!r} is a {kind}; the bench maps {', '.join(SHAPES)}")
    if kind == "plane":
        return bullet.createCollisionShape(bullet.GEOM_PLANE, planeNormal=[0, 0, 1], physicsClientId=client)
    if kind == "box":
        return bullet.createCollisionShape(bullet.GEOM_BOX, halfExtents=[v / 2 for v in obj.size],
                                           physicsClientId=client)
    if kind == "sphere":
        return bullet.createCollisionShape(bullet.GEOM_SPHERE, radius=obj.radius, physicsClientId=client)
    return bullet.createCollisionShape(bullet.GEOM_CYLINDER, radius=obj.radius, height=obj.height,
                                       physicsClientId=client)


def _starts(scene, state: dict | None) -> dict:
    """Each movable object's start (``initial_state`` terms), the source's from ``state``
    (``{"source", "initial_state"}`` as a solve's result.json has them) where given."""
    out = {o.id: {"position": o.pose.position, "orientation": o.pose.orientation,
                  "linear_velocity": o.velocity.linear, "angular_velocity": o.velocity.angular}
           for o in scene.movable}
    if state is not None:
        out[state["source"]] = {**out[state["source"]], **state["initial_state"]}
    return out


def bullet_run(scene, times, state: dict | None = None, timestep: float | None = None) -> dict:
    """Bullet's object-frame origins and orientations of every movable object at ``times`` (s), at
    ``timestep`` (default ``BULLET_TIMESTEP``); ``state``: the source's start replaced (``_starts``).

    Returns:
        {t: (positions (N, 3), orientations (N, 4) w x y z)}, N the scene's movable objects.
    Raises:
        ValueError: a shape Bullet is not given here, or an impossible material.
    """
    import pybullet as bullet

    from dejaview.io.mjcf import _mass_properties

    dt = float(timestep or BULLET_TIMESTEP)
    sim = scene.simulation
    starts = _starts(scene, state)
    client = bullet.connect(bullet.DIRECT)
    try:
        bullet.setGravity(*scene.gravity, physicsClientId=client)
        bullet.setPhysicsEngineParameter(fixedTimeStep=dt, numSubSteps=0, numSolverIterations=SOLVER_ITERATIONS,
                                         restitutionVelocityThreshold=RESTITUTION_THRESHOLD,
                                         deterministicOverlappingPairs=1, **CONTACT, physicsClientId=client)
        ids = []
        for obj in scene.objects:
            mu = sim.friction if obj.friction is None else obj.friction
            e = sim.restitution if obj.restitution is None else obj.restitution
            shape = _shape(bullet, client, obj)
            if obj.fixed:
                body = bullet.createMultiBody(0.0, shape, basePosition=list(obj.pose.position),
                                              baseOrientation=_xyzw(obj.pose.orientation), physicsClientId=client)
                bullet.changeDynamics(body, -1, **material(mu, e), physicsClientId=client)
                continue
            props = _mass_properties(scene, obj)
            if np.linalg.norm(props.center_of_mass) > 1e-12:
                raise ValueError(f"Bullet: object {obj.id!r}'s centre of mass is off its origin")
            s = starts[obj.id]
            body = bullet.createMultiBody(float(props.mass), shape, basePosition=list(s["position"]),
                                          baseOrientation=_xyzw(s["orientation"]), physicsClientId=client)
            bullet.changeDynamics(body, -1, **material(mu, e),
                                  localInertiaDiagonal=np.diag(props.inertia).tolist(), physicsClientId=client)
            bullet.resetBaseVelocity(body, list(s["linear_velocity"]), list(s["angular_velocity"]),
                                     physicsClientId=client)
            ids.append(body)
        marks = {round(t / dt): t for t in times}
        out = {}
        for k in range(max(marks) + 1):
            if k in marks:
                poses = [bullet.getBasePositionAndOrientation(b, physicsClientId=client) for b in ids]
                out[marks[k]] = (np.array([p for p, _ in poses]),
                                 np.array([(q[3], q[0], q[1], q[2]) for _, q in poses]))
            bullet.stepSimulation(physicsClientId=client)
        return out
    finally:
        bullet.disconnect(physicsClientId=client)
