"""Build the bundled example scenes: each tells a story with a known true past.

For every scene the true initial state of the source is simulated with
DejaView, and the source's final pose becomes the ``<target>``; the scene file
itself holds a deliberately wrong initial guess (the pose a robot might
assume), so ``dejaview solve`` has real work to do. The true initial state is
written beside the scene as ``<name>.truth.json`` (for tests and benchmarks).

Run from the repository root after ``examples/build_meshes.py``:

    python examples/make_scenes.py
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import torch

from dejaview.scene import (
    HeatmapSettings,
    InferenceSettings,
    JointKeyframe,
    Optimize,
    Penalty,
    Pose,
    Scene,
    SceneObject,
    SimulationSettings,
    StartArea,
    Target,
    Observation,
    PhysicsPrior,
    Velocity,
)
from dejaview.sim import World
from dejaview.sim.build import initial_state
from dejaview.sim.integrate import rollout
from dejaview.sim.rotation import quat_multiply, rotvec_to_quat

HERE = Path(__file__).resolve().parent
SCENES = HERE / "scenes"


def floor() -> SceneObject:
    return SceneObject(id="floor", shape="plane", fixed=True)


def furniture(name: str) -> SceneObject:
    return SceneObject(id=name, mesh=f"../meshes/{name}.obj", fixed=True)


def movable(name: str, mesh: str, position, orientation=(1.0, 0.0, 0.0, 0.0), linear=(0.0, 0.0, 0.0),
            angular=(0.0, 0.0, 0.0), mass=None) -> SceneObject:
    return SceneObject(id=name, mesh=f"../meshes/{mesh}.obj", spheres=f"../packings/{mesh}.spheres",
                       mass=mass, pose=Pose(tuple(position), tuple(orientation)),
                       velocity=Velocity(tuple(linear), tuple(angular)))


def with_truth(scene: Scene, truth: SceneObject, guess: SceneObject, engine: str = "torch",
               **target_kw) -> tuple[Scene, dict]:
    """Simulate the scene with the source's true start; return the scene holding the guess
    and a target at the simulated end, plus the truth record (``engine``: the rollout's)."""
    scene = replace(scene, base_dir=SCENES)
    true_scene = scene.with_object(truth)
    world = World.from_scene(true_scene)
    with torch.no_grad():
        traj = rollout(world, initial_state(world, true_scene), engine=engine)
    src = world.body_index(truth.id)
    end_pos = world.object_position(traj.final)[0, src].tolist()
    end_q = traj.final.orientation[0, src].tolist()
    target = Target(position=tuple(round(v, 6) for v in end_pos),
                    orientation=tuple(round(v, 6) for v in end_q), **target_kw)
    inf = replace(scene.inference, targets=(target,))
    out = replace(scene.with_object(guess), inference=inf)
    record = {"source": truth.id,
              "initial_state": {"position": list(truth.pose.position),
                                "orientation": list(truth.pose.orientation),
                                "linear_velocity": list(truth.velocity.linear),
                                "angular_velocity": list(truth.velocity.angular)},
              "final_pose": {"position": end_pos, "orientation": end_q}}
    return out, record


def ball_off_table():
    """A ball rolled across a table, off its edge, onto the floor (seen rolling there: moving)."""
    truth = movable("ball", "ball", (0.25, 0.05, 0.80), linear=(1.2, 0.15, 0.0),
                    angular=(-3.0, 24.0, 0.0), mass=0.4)
    guess = movable("ball", "ball", (0.0, 0.0, 0.80), linear=(0.5, 0.0, 0.0), mass=0.4)
    scene = Scene(
        name="ball-off-the-table",
        objects=(floor(), furniture("table"), truth),
        simulation=SimulationSettings(dt=0.002, duration=1.2, friction=0.5, restitution=0.3),
        inference=InferenceSettings(
            source="ball", targets=(Target((0, 0, 0)),),
            loss="position", evaluate="best",
            optimize=Optimize(position=True, orientation=False, linear_velocity=True,
                              angular_velocity=True),
            start_area=StartArea((-0.5, -0.3, 0.80), (0.5, 0.3, 0.80)),
            heatmap=HeatmapSettings(cells=(8, 6), samples=4, sigma=0.02)))
    return with_truth(scene, truth, guess, moving=True)  # seen rolling on the floor (balls roll on)


def mug_off_counter():
    """A mug knocked off a kitchen counter: it slides, tips over the edge, tumbles on the floor and comes to rest there (seen lying still)."""
    # 2.05 m/s (2.0 until 2026-12-07): with restitution's blend over the impact's phase the mug slid
    # off at 2.0 m/s lands on its side and rolls back upright in its last second; at 1.95 and 2.05 m/s
    # it stays lying, as the story says
    truth = movable("mug", "mug", (0.30, 0.02, 0.95), linear=(2.05, 0.2, 0.0), angular=(0.0, 0.0, 2.0),
                    mass=0.35)
    guess = movable("mug", "mug", (0.0, 0.0, 0.95), linear=(0.5, 0.0, 0.0), mass=0.35)
    scene = Scene(
        name="mug-off-the-counter",
        objects=(floor(), furniture("counter"), truth),
        simulation=SimulationSettings(dt=0.002, duration=2.2, friction=0.5, restitution=0.2),
        inference=InferenceSettings(
            source="mug", targets=(Target((0, 0, 0)),),
            loss="pose", evaluate="best",
            start_area=StartArea((-0.4, -0.25, 0.95), (0.45, 0.25, 0.95)),
            heatmap=HeatmapSettings(cells=(8, 6), samples=4, sigma=0.02)))
    return with_truth(scene, truth, guess)


def box_along_shelf():
    """A box slid along a shelf board into the corner wall."""
    truth = movable("box", "box", (-0.25, -0.02, 1.05), linear=(2.6, 0.05, 0.0), mass=0.8)
    guess = movable("box", "box", (-0.1, 0.0, 1.05), linear=(1.0, 0.0, 0.0), mass=0.8)
    scene = Scene(
        name="box-along-the-shelf",
        objects=(floor(), furniture("shelf"), truth),
        simulation=SimulationSettings(dt=0.002, duration=1.0, friction=0.4, restitution=0.1),
        inference=InferenceSettings(
            source="box", targets=(Target((0, 0, 0)),),
            loss="pose", evaluate="best",
            optimize=Optimize(position=True, orientation=False, linear_velocity=True,
                              angular_velocity=False),
            start_area=StartArea((-0.4, -0.06, 1.05), (0.2, 0.04, 1.05)),
))
    return with_truth(scene, truth, guess)


def box_among_boxes():
    """A box thrown onto the floor among three others, knocking into them."""
    truth = movable("thrown", "box", (0.0, 0.0, 0.6), linear=(1.6, 0.1, 0.5), angular=(1.0, 2.0, 0.5),
                    mass=0.8)
    guess = movable("thrown", "box", (0.0, 0.0, 0.6), linear=(1.0, 0.0, 0.0), mass=0.8)
    others = tuple(movable(f"box{i}", "box", p, mass=0.8)
                   for i, p in enumerate([(0.75, 0.0, 0.05), (0.75, 0.2, 0.05), (1.0, 0.1, 0.05)]))
    scene = Scene(
        name="box-among-boxes",
        objects=(floor(), truth, *others),
        simulation=SimulationSettings(dt=0.002, duration=1.5, friction=0.5, restitution=0.1),
        inference=InferenceSettings(
            source="thrown", targets=(Target((0, 0, 0)),),
            loss="pose", evaluate="best",
            start_area=StartArea((-0.3, -0.3, 0.4), (0.3, 0.3, 0.8)),
            penalties=(Penalty(("thrown", "box0"), 0.1),)))
    return with_truth(scene, truth, guess)


def box_hits_arm():
    """A box thrown at a robot arm standing in a known pose (joints from its controller): it hits the
    forearm, flies over and lands behind. Where was it thrown from?"""
    arm = SceneObject(id="arm", urdf="../robots/arm.urdf", joints=(0.0, 0.35, -0.35), fixed=True)
    truth = movable("box", "box", (0.45, -0.5, 0.6), linear=(0.3, 1.6, 0.8), angular=(0.5, 1.0, 0.3),
                    mass=0.8)
    guess = movable("box", "box", (0.45, -0.55, 0.6), linear=(0.0, 1.0, 0.0), mass=0.8)
    scene = Scene(
        name="box-hits-arm",
        objects=(floor(), arm, truth),
        simulation=SimulationSettings(dt=0.002, duration=1.5, friction=0.5, restitution=0.1),
        inference=InferenceSettings(
            source="box", targets=(Target((0, 0, 0)),),
            loss="pose", evaluate="best",
            start_area=StartArea((0.2, -0.75, 0.6), (0.7, -0.35, 0.6)),
            heatmap=HeatmapSettings(cells=(6, 4), samples=2, sigma=0.02)))
    return with_truth(scene, truth, guess)


SWEEP = ((0.0, (-1.0, 0.1253, -0.1253)), (0.9, (0.9, 0.1253, -0.1253)))
"""The arm's sweep (time s, joint values: shoulder yaw, shoulder pitch, elbow): the upper arm and the
forearm level 5 cm above the table, turning from -1.0 to 0.9 rad about the base in 0.9 s."""


def arm_sweeps_mug():
    """A robot arm, replaying a logged joint trajectory, sweeps across a table and knocks a mug off
    it; the mug is found lying on the floor. Where on the table did the mug stand?"""
    arm = SceneObject(id="arm", urdf="../robots/arm.urdf", fixed=True,
                      keyframes=tuple(JointKeyframe(t, q) for t, q in SWEEP))
    table = SceneObject(id="table", shape="box", size=(0.4, 0.7, 0.3), fixed=True,
                        pose=Pose((0.5, -0.05, 0.15)))
    truth = movable("mug", "mug", (0.55, -0.08, 0.35), mass=0.35)
    guess = movable("mug", "mug", (0.45, -0.15, 0.35), mass=0.35)
    scene = Scene(
        name="arm-sweeps-mug",
        objects=(floor(), table, arm, truth),
        simulation=SimulationSettings(dt=0.002, duration=4.0, friction=0.5, restitution=0.2),
        inference=InferenceSettings(
            source="mug", targets=(Target((0, 0, 0)),),
            loss="pose", evaluate="final",
            optimize=Optimize(position=True, orientation=False, linear_velocity=False,
                              angular_velocity=False),
            start_area=StartArea((0.38, -0.3, 0.35), (0.66, 0.1, 0.35)),
            heatmap=HeatmapSettings(cells=(7, 10), samples=1, sigma=0.02)))
    return with_truth(scene, truth, guess, engine="native")


TRACKED_TIMES = (0.15, 0.35, 0.6)
"""Moments a tracker saw the tossed box in flight (s); it is seen again lying still at the end."""


def box_tossed_tracked():
    """A box tossed onto the floor, tracked by a camera: seen at 0.15 s and 0.35 s (position only,
    mid-air), at 0.6 s (pose) and lying still at the end (pose); the tracker's noise is 1 cm and 0.1
    rad. Where was it tossed from, and how?"""
    truth = movable("box", "box", (0.05, -0.1, 0.55), orientation=(0.9659, 0.0, 0.2588, 0.0),
                    linear=(1.4, 0.35, 1.2), angular=(1.5, -3.0, 2.0), mass=0.8)
    guess = movable("box", "box", (0.0, 0.0, 0.5), linear=(1.0, 0.0, 0.5), mass=0.8)
    scene = Scene(
        name="box-tossed-tracked",
        objects=(floor(), truth),
        simulation=SimulationSettings(dt=0.002, duration=1.2, friction=0.5, restitution=0.1),
        inference=InferenceSettings(
            source="box", targets=(Target((0, 0, 0)),), loss="pose",
            start_area=StartArea((-0.25, -0.3, 0.4), (0.25, 0.2, 0.7)),
            observation=Observation(sigma=0.01, angle_sigma=0.1)))
    scene = replace(scene, base_dir=SCENES)
    true_scene = scene.with_object(truth)
    world = World.from_scene(true_scene)
    with torch.no_grad():
        traj = rollout(world, initial_state(world, true_scene))
    src = world.body_index(truth.id)
    noise = torch.Generator().manual_seed(7)  # the tracker's errors, drawn once from its noise model
    targets, seen = [], []
    for k, t in enumerate((*TRACKED_TIMES, None)):
        i = -1 if t is None else int(round(t / world.dt))
        origin = world.object_position(traj.states)[i, 0, src]
        q = traj.states.orientation[i, 0, src]
        origin = origin + 0.01 * torch.randn(3, generator=noise, dtype=origin.dtype)
        q = quat_multiply(rotvec_to_quat(0.1 * torch.randn(3, generator=noise, dtype=q.dtype)), q)
        pose_seen = k >= 2
        targets.append(Target(position=tuple(round(v, 4) for v in origin.tolist()),
                              orientation=tuple(round(v, 5) for v in q.tolist()) if pose_seen else None,
                              time=t if t is not None else scene.simulation.duration,
                              moving=None if t is not None else False))  # the end: lying still
        seen.append({"time": float(traj.steps[i]) * world.dt, "position": origin.tolist(),
                     "orientation": q.tolist() if pose_seen else None})
    out = replace(scene.with_object(guess), inference=replace(scene.inference, targets=tuple(targets)))
    record = {"source": truth.id,
              "initial_state": {"position": list(truth.pose.position),
                                "orientation": list(truth.pose.orientation),
                                "linear_velocity": list(truth.velocity.linear),
                                "angular_velocity": list(truth.velocity.angular)},
              "observed": seen,
              "final_pose": {"position": world.object_position(traj.final)[0, src].tolist(),
                             "orientation": traj.final.orientation[0, src].tolist()}}
    return out, record


THROWS = (  # the true starts of the three throws: position, orientation, linear and angular velocity
    ((-0.3, 0.0, 0.6), (0.9659, 0.0, 0.2588, 0.0), (1.6, 0.2, 0.8), (2.0, -4.0, 1.0)),
    ((0.0, -0.3, 0.4), (0.9239, 0.3827, 0.0, 0.0), (0.4, 1.8, 1.2), (-3.0, 1.0, 2.5)),
    ((0.2, 0.2, 0.8), (1.0, 0.0, 0.0, 0.0), (-1.2, -0.6, 0.0), (0.0, 3.0, -2.0)),
)
THROW_PHYSICS = {"friction": 0.38, "restitution": 0.45}
"""The floor's true friction and restitution in the three throws; the scenes say 0.5 and 0.3."""
THROW_TIMES = (0.1, 0.25, 0.4, 0.55, 0.7, 0.9)


def box_throws():
    """Three throws of the same box onto the same floor, each tracked by a camera (pose at six
    moments, 5 mm and 0.05 rad noise) and lying still at the end: what are the floor's friction and
    restitution? (``dejaview identify``; the scenes carry the nominal 0.5 and 0.3.)"""
    scenes, records = [], []
    noise = torch.Generator().manual_seed(11)  # the tracker's errors, drawn once from its noise model
    for k, (pos, q0, lin, ang) in enumerate(THROWS):
        truth = movable("box", "box", pos, orientation=q0, linear=lin, angular=ang, mass=0.8)
        guess = movable("box", "box", (0.0, 0.0, 0.5), mass=0.8)
        nominal = Scene(
            name=f"box-throw-{k + 1}",
            objects=(floor(), truth),
            simulation=SimulationSettings(dt=0.002, duration=1.5, friction=0.5, restitution=0.3),
            inference=InferenceSettings(
                source="box", targets=(Target((0, 0, 0)),), loss="pose",
                start_area=StartArea((-0.5, -0.5, 0.3), (0.5, 0.5, 0.9)),
                observation=Observation(sigma=0.005, angle_sigma=0.05),
                physics_prior=PhysicsPrior(friction=0.5, restitution=0.5)))
        nominal = replace(nominal, base_dir=SCENES)
        true_scene = replace(nominal.with_object(truth),
                             simulation=replace(nominal.simulation, **THROW_PHYSICS))
        world = World.from_scene(true_scene)
        with torch.no_grad():
            traj = rollout(world, initial_state(world, true_scene))
        targets, seen = [], []
        for t in (*THROW_TIMES, None):
            i = -1 if t is None else int(round(t / world.dt))
            origin = world.object_position(traj.states)[i, 0, 0]
            q = traj.states.orientation[i, 0, 0]
            origin = origin + 0.005 * torch.randn(3, generator=noise, dtype=origin.dtype)
            q = quat_multiply(rotvec_to_quat(0.05 * torch.randn(3, generator=noise, dtype=q.dtype)), q)
            targets.append(Target(position=tuple(round(v, 5) for v in origin.tolist()),
                                  orientation=tuple(round(v, 5) for v in q.tolist()),
                                  time=t if t is not None else nominal.simulation.duration,
                                  moving=None if t is not None else False))
            seen.append({"time": float(traj.steps[i]) * world.dt, "position": origin.tolist(), "orientation": q.tolist()})
        scenes.append(replace(nominal.with_object(guess), inference=replace(nominal.inference, targets=tuple(targets))))
        records.append({"scene": f"box_throw_{k + 1}.xml", "initial_state": {
            "position": list(pos), "orientation": list(q0), "linear_velocity": list(lin), "angular_velocity": list(ang)},
            "observed": seen})
    return scenes, {"source": "box", "physics": dict(THROW_PHYSICS), "throws": records}


def write_box_throws():
    """examples/scenes/box_throw_{1,2,3}.xml and box_throws.truth.json."""
    scenes, truth = box_throws()
    for k, scene in enumerate(scenes):
        path = SCENES / f"box_throw_{k + 1}.xml"
        text = scene.to_xml().replace("?>\n", f"?>\n<!-- {box_throws.__doc__.strip()} -->\n", 1)
        path.write_text(text, encoding="utf-8")
        Scene.from_xml(path)  # validates
        print(path)
    (SCENES / "box_throws.truth.json").write_text(json.dumps(truth, indent=2), encoding="utf-8")


RAMP_ANGLE = math.radians(20.0)


def ramp() -> SceneObject:
    """A 1.0 x 0.8 x 0.05 m board tilted 20 degrees about y, sloping down towards +x; its top
    surface runs from z ~ 0.5 m (x = -0.47) to z ~ 0.16 m (x = +0.47), then a step to the floor."""
    half = RAMP_ANGLE / 2.0
    return SceneObject(id="ramp", shape="box", size=(1.0, 0.8, 0.05), fixed=True,
                       pose=Pose((0.0, 0.0, 0.3), (math.cos(half), 0.0, math.sin(half), 0.0)))


def ramp_scene(name: str, truth: SceneObject, guess: SceneObject, *, dt: float, duration: float,
               area, cells, samples: int, sigma: float, loss: str, optimize: Optimize, extra: dict,
               friction: float, **target_kw):
    scene = Scene(
        name=name,
        objects=(floor(), ramp(), truth),
        simulation=SimulationSettings(dt=dt, duration=duration, friction=friction, restitution=0.2,
                                      extra=extra),
        inference=InferenceSettings(
            source=truth.id, targets=(Target((0, 0, 0)),), iterations=60,
            loss=loss, evaluate="final", optimize=optimize,
            start_area=StartArea(*area),
            heatmap=HeatmapSettings(cells=cells, samples=samples, sigma=sigma)))
    return with_truth(scene, truth, guess, **target_kw)


def ball_down_ramp():
    """A ball let go at rest above a ramp: it drops onto it, rolls down and off onto the floor. Seen 1.2 s later: where was it let go?"""
    truth = movable("ball", "ball", (-0.27, 0.08, 0.55), mass=0.4)
    guess = movable("ball", "ball", (-0.2, 0.0, 0.55), mass=0.4)
    return ramp_scene("ball-down-the-ramp", truth, guess, dt=0.005, duration=1.2,
                      area=((-0.4, -0.25, 0.55), (0.0, 0.25, 0.55)), cells=(8, 10), samples=2,
                      sigma=0.02, loss="position",
                      optimize=Optimize(position=True, orientation=False, linear_velocity=False,
                                        angular_velocity=False),
                      extra={"substeps": "1", "contact-frequency": "100", "unload-velocity": "0.05"}, friction=0.5,
                      time=1.2)  # seen at that moment, rolling


def box_down_ramp():
    """A box let go on a ramp: it slides down, off onto the floor, and comes to rest. Where was it let go?"""
    truth = SceneObject(id="box", mesh="../meshes/box.obj", spheres="../packings/box_coarse.spheres",
                        mass=0.8, pose=Pose((-0.22, -0.1, 0.56),
                                            (math.cos(RAMP_ANGLE / 2), 0.0, math.sin(RAMP_ANGLE / 2), 0.0)))
    guess = replace(truth, pose=replace(truth.pose, position=(-0.2, 0.0, 0.56)))
    return ramp_scene("box-down-the-ramp", truth, guess, dt=0.005, duration=2.0,
                      area=((-0.4, -0.25, 0.56), (0.0, 0.25, 0.56)), cells=(8, 10), samples=2,
                      sigma=0.02, loss="pose",
                      optimize=Optimize(position=True, orientation=False, linear_velocity=False,
                                        angular_velocity=False),
                      extra={"substeps": "1", "contact-frequency": "100", "unload-velocity": "0.05"}, friction=0.25)


BUILDERS = {
    "ball_off_table": ball_off_table,
    "mug_off_counter": mug_off_counter,
    "box_along_shelf": box_along_shelf,
    "box_among_boxes": box_among_boxes,
    "box_hits_arm": box_hits_arm,
    "arm_sweeps_mug": arm_sweeps_mug,
    "ball_down_ramp": ball_down_ramp,
    "box_down_ramp": box_down_ramp,
    "box_tossed_tracked": box_tossed_tracked,
}


def main(names=None):
    SCENES.mkdir(exist_ok=True)
    for name in names or BUILDERS:
        scene, truth = BUILDERS[name]()
        path = SCENES / f"{name}.xml"
        text = scene.to_xml().replace("?>\n", f"?>\n<!-- {BUILDERS[name].__doc__.strip()} -->\n", 1)
        path.write_text(text, encoding="utf-8")
        (SCENES / f"{name}.truth.json").write_text(json.dumps(truth, indent=2), encoding="utf-8")
        Scene.from_xml(path)  # validates
        print(f"{path}: target {scene.inference.target.position}")


if __name__ == "__main__":
    import sys

    if sys.argv[1:] == ["box_throws"]:
        write_box_throws()
    else:
        main(sys.argv[1:] or None)
