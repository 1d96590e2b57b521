"""A moving robot in an MJCF export: mocap bodies driven by a keyframe sequence.

A robot with ``<joints time values>`` keyframes (``dejaview.sim.motion``) moves kinematically; MuJoCo's
kinematic bodies are mocap bodies (children of the world, no joints, posed by ``data.mocap_pos`` and
``data.mocap_quat``). ``export_mjcf`` writes each link geometry of such a robot as a mocap body
named after it (``arm/forearm``) holding its geom, and the motion as keyframes ``motion-0000``,
``motion-0001``, ...: the links' poses (``mpos``, ``mquat``) by DejaView's forward kinematics at
their ``time``, every ``MOTION_INTERVAL`` from 0 to the last joint keyframe (joints interpolated
linearly in between are not poses interpolated linearly, hence the sampling). The ``initial``
keyframe holds their poses at time 0. MJCF keeps no trajectory a model follows by itself, so a
replay sets the mocap poses before each step (``drive_mocap``)::

    mujoco.mj_resetDataKeyframe(model, data, model.key("initial").id)
    while data.time < 2.0:
        drive_mocap(model, data)
        mujoco.mj_step(model, data)

Not the same contact as DejaView's: MuJoCo gives a mocap body no velocity in its contacts (it
pushes by where it is, step after step), where DejaView takes a link's velocity off the contact's.
"""

from __future__ import annotations

import numpy as np

MOTION_INTERVAL = 0.01
"""s between two motion keyframes of the export."""

MOTION_KEY = "motion-"
"""Name prefix of the motion keyframes."""


def motion_times(scene) -> np.ndarray:
    """Times (s) of the motion keyframes: every ``MOTION_INTERVAL`` up to the last joint keyframe of
    any moving robot (``dejaview.sim.motion.sample_times``)."""
    from dejaview.sim.motion import sample_times

    last = max((obj.keyframes[-1].time for obj in scene.objects if obj.moving), default=0.0)
    return sample_times(last, MOTION_INTERVAL)


def mocap_bodies(link_geoms: list[tuple[object, list[str]]]) -> list[str]:
    """``<body mocap="true">`` elements, one per link geometry: (the link's fixed SceneObject posed
    at time 0, its ``<geom>`` elements in its own frame)."""
    from dejaview.io.mjcf_text import _vec, _xml

    return [f'<body name="{_xml(one.id)}" mocap="true" pos="{_vec(one.pose.position)}" '
            f'quat="{_vec(one.pose.orientation)}">{"".join(geoms)}</body>' for one, geoms in link_geoms]


def motion_keys(scene, names: list[str]) -> tuple[str, list[str]]:
    """The ``mpos``/``mquat`` attributes of the ``initial`` keyframe and the motion keyframes'
    ``<key>`` elements, the mocap bodies in ``names`` order (every moving robot's link geometries)."""
    from dejaview.io.mjcf_text import _num, _vec

    from dejaview.sim.motion import link_poses

    times = motion_times(scene)
    poses = {}
    for obj in scene.objects:
        if obj.moving:
            poses.update(link_poses(scene, obj, times))
    pos = np.stack([poses[n][0] for n in names], 1)  # (T, M, 3)
    quat = np.stack([poses[n][1] for n in names], 1)  # (T, M, 4)
    initial = f' mpos="{_vec(pos[0].ravel())}" mquat="{_vec(quat[0].ravel())}"'
    keys = [f'<key name="{MOTION_KEY}{j:04d}" time="{_num(t)}" mpos="{_vec(pos[j].ravel())}" '
            f'mquat="{_vec(quat[j].ravel())}"/>' for j, t in enumerate(times)]
    return initial, keys


def drive_mocap(model, data) -> None:
    """Set ``data.mocap_pos`` and ``data.mocap_quat`` to the motion keyframes' poses at ``data.time``:
    positions interpolated linearly, orientations by spherical interpolation (the keyframes lie
    ``MOTION_INTERVAL`` apart), the last held after the end."""
    import mujoco

    keys = [k for k in range(model.nkey) if mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_KEY, k)
            .startswith(MOTION_KEY)]
    if not keys:
        return
    times = np.array([model.key_time[k] for k in keys])
    j = int(np.clip(np.searchsorted(times, data.time, side="right") - 1, 0, len(keys) - 1))
    k = min(j + 1, len(keys) - 1)
    u = 0.0 if k == j else float(np.clip((data.time - times[j]) / (times[k] - times[j]), 0.0, 1.0))
    a, b = keys[j], keys[k]
    data.mocap_pos[:] = (1 - u) * model.key_mpos[a].reshape(-1, 3) + u * model.key_mpos[b].reshape(-1, 3)
    qa, qb = model.key_mquat[a].reshape(-1, 4), model.key_mquat[b].reshape(-1, 4)
    for m in range(qa.shape[0]):
        q1 = qb[m] if np.dot(qa[m], qb[m]) >= 0 else -qb[m]
        data.mocap_quat[m] = _slerp(qa[m], q1, u)


def _slerp(a: np.ndarray, b: np.ndarray, u: float) -> np.ndarray:
    dot = float(np.clip(np.dot(a, b), -1.0, 1.0))
    if dot > 0.9995:
        q = a + u * (b - a)
    else:
        th = np.arccos(dot)
        q = (np.sin((1 - u) * th) * a + np.sin(u * th) * b) / np.sin(th)
    return q / np.linalg.norm(q)
