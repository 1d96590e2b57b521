"""Trajectory CSV (scene-format spec, "Outputs").

One row per object per recorded step, header
``step,time,object,x,y,z,qw,qx,qy,qz``; positions are object-frame origins
(as in scene files), not centres of mass. Fixed objects are left out.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import torch

from dejaview.errors import SimulationError

HEADER = ("step", "time", "object", "x", "y", "z", "qw", "qx", "qy", "qz")


def trajectory_rows(world, traj, batch_index: int = 0):
    """Yield CSV rows (tuples) of one batch element of a Trajectory.

    Args:
        world: the World (body names, centre-of-mass offsets).
        traj: Trajectory with states (T, B, N, ...).
        batch_index: which candidate of the batch to write.
    Raises:
        SimulationError: a non-finite number, naming the object and the step (never written: the
            forward simulation's divergence check, ``dejaview.sim.divergence``, stops such runs
            first; this guards every other writer).
    """
    states = traj.states
    with torch.no_grad():
        pos = states.position[:, batch_index]  # (T, N, 3)
        q = states.orientation[:, batch_index]
        com = world.com.to(pos.dtype)
        from dejaview.sim.rotation import quat_rotate

        origin = (pos - quat_rotate(q, com.expand_as(pos))).cpu().double().numpy()
        q = q.cpu().double().numpy()
    steps = traj.steps.tolist()
    finite = np.isfinite(origin).all(-1) & np.isfinite(q).all(-1)  # (T, N)
    if not finite.all():
        t, i = (int(v) for v in np.argwhere(~finite)[0])
        raise SimulationError(f"trajectory of object {world.names[i]!r} is not finite at step {steps[t]} "
                              f"(t = {steps[t] * traj.dt:.6g} s); nothing written")
    for t, step in enumerate(steps):
        time = step * traj.dt
        for i, name in enumerate(world.names):
            x, y, z = origin[t, i]
            qw, qx, qy, qz = q[t, i]
            yield (step, f"{time:.6f}", name, *(f"{v:.9g}" for v in (x, y, z, qw, qx, qy, qz)))


def trajectory_csv(world, traj, batch_index: int = 0) -> str:
    """The trajectory CSV of one candidate as text."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(HEADER)
    writer.writerows(trajectory_rows(world, traj, batch_index))
    return buf.getvalue()


def write_trajectory_csv(path, world, traj, batch_index: int = 0) -> Path:
    """Write ``trajectory_csv`` to ``path`` (folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(trajectory_csv(world, traj, batch_index), encoding="utf-8")
    return path


def read_trajectory_csv(path_or_text) -> dict[str, dict[str, list]]:
    """Read a trajectory CSV into ``{object: {"step": [...], "time": [...], "position": [[x,y,z]...],
    "orientation": [[w,x,y,z]...]}}`` (for tests and clients)."""
    text = path_or_text
    if isinstance(path_or_text, Path) or (isinstance(path_or_text, str) and "\n" not in path_or_text):
        text = Path(path_or_text).read_text(encoding="utf-8")
    reader = csv.reader(io.StringIO(text))
    header = tuple(next(reader))
    if header != HEADER:
        raise ValueError(f"not a trajectory CSV: header {header}")
    out: dict[str, dict[str, list]] = {}
    for row in reader:
        rec = out.setdefault(row[2], {"step": [], "time": [], "position": [], "orientation": []})
        rec["step"].append(int(row[0]))
        rec["time"].append(float(row[1]))
        rec["position"].append([float(v) for v in row[3:6]])
        rec["orientation"].append([float(v) for v in row[6:10]])
    return out
