"""DejaView against MuJoCo with finite differences, side by side in one process (issue 25).

    python bench/peers.py                 # N = 1, 2, 4, 8, 16, the mug, the 1024-candidate memory
    python bench/peers.py --quick         # N = 1, 2 and 50 steps (smoke test)
    dejaview bench peers [--quick] [--csv FILE] [--check]

The scene (``box_scene``): a table (1.6 x 0.8 m, top at 0.7 m) on a floor; a
box (0.2 x 0.15 x 0.1 m, 0.8 kg; DejaView packs it with
``examples/packings/box.spheres``, 128 spheres, MuJoCo models it as a box
geom) is thrown from above the table's near end, lands on the table and
slides across it, off its far edge onto the floor; N - 1 more boxes rest on
the table in its way (rows of four across its path, the first row 0.55 m
ahead of its landing point), and it knocks into them. 750 steps of 2 ms (both engines: MuJoCo
runs at the same step, ``implicitfast``, elliptic cones, the contact mapping
of ``dejaview.io.mjcf``). The thrown box's initial state has 12 free
parameters (position, rotation vector, linear and angular velocity); the loss
is the pose loss of its final state.

Per N, best of ``repeats`` runs (more for short calls: ``_best_time``), B = 1:

- ``dv rollout``: a DejaView rollout without gradient (native engine), recording what the loss
  reads (the final state, as MuJoCo's rollout);
- ``dv loss+grad``: one exact loss + gradient of the 12 parameters (reverse mode,
  ``SpheresProblem.value_and_grad``), and its ratio to the rollout;
- ``mj rollout``: a MuJoCo rollout (``mj_step`` with ``nstep``, no Python per step);
- ``mj fd grad``: MuJoCo's loss + finite-difference gradient (13 rollouts, forward
  differences), and the ratio ``mj fd grad / dv loss+grad``.

Then the mug reference scene (``examples/scenes/mug_off_counter.xml``, as shipped, DejaView
only): the same two timings at B = 1 and per candidate at B = 64; and the peak memory a
1024-candidate loss + gradient of the mug adds (VmHWM reset before it, Linux), by default
at 750 records (``--memory-batch`` changes the batch).

The targets of issue 25 (``--check``: exit 1 when one is missed): the exact gradient at
least 3x faster than MuJoCo's finite differences at every N, a rollout at least as fast as
MuJoCo's at N = 1, the gradient at most 4x the rollout at every N.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MUG = ROOT / "examples" / "scenes" / "mug_off_counter.xml"
COUNTS = (1, 2, 4, 8, 16)
BOX = (0.2, 0.15, 0.1)
BOX_MASS = 0.8
TABLE = (1.6, 0.8, 0.7)
FRICTION, RESTITUTION = 0.5, 0.1
DT, STEPS = 0.002, 750
THROW = dict(position=(-0.75, 0.0, 0.85), linear=(4.0, 0.0, 0.3), angular=(0.0, 2.0, 1.0))
ORIENTATION_WEIGHT = 0.05  # metres per radian, as the pose loss
FD_EPS = 1e-6
TARGET_GRAD_SPEEDUP = 3.0
TARGET_GRAD_OVER_ROLLOUT = 4.0


def resting_positions(count: int) -> list[tuple[float, float, float]]:
    """Where the boxes in the thrown box's way rest on the table: rows of four across its path."""
    ys = (0.09, -0.09, 0.27, -0.27)
    return [(0.22 * (i // 4), ys[i % 4], TABLE[2] + BOX[2] / 2) for i in range(count)]


def box_scene(n: int, steps: int = STEPS) -> str:
    """Scene XML of the thrown box with ``n - 1`` boxes in its way (module docstring)."""
    mesh, packing = "../meshes/box.obj", "../packings/box.spheres"

    def box(oid, pos, linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0)):
        v = lambda t: " ".join(f"{x:g}" for x in t)  # noqa: E731
        return (f'<object id="{oid}" mesh="{mesh}" spheres="{packing}" mass="{BOX_MASS:g}">'
                f'<pose position="{v(pos)}" orientation="1 0 0 0"/>'
                f'<velocity linear="{v(linear)}" angular="{v(angular)}"/></object>')

    p = THROW["position"]
    others = "".join(box(f"box{i}", pos) for i, pos in enumerate(resting_positions(n - 1)))
    return f"""<?xml version='1.0' encoding='UTF-8'?>
<scene version="1" name="box-across-table-{n}" gravity="0 0 -9.81">
  <simulation dt="{DT:g}" duration="{steps * DT:.6g}" friction="{FRICTION:g}" restitution="{RESTITUTION:g}"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
  <object id="table" shape="box" size="{TABLE[0]:g} {TABLE[1]:g} {TABLE[2]:g}" fixed="true">
    <pose position="0 0 {TABLE[2] / 2:g}" orientation="1 0 0 0"/></object>
  {box("thrown", p, THROW["linear"], THROW["angular"])}
  {others}
  <inference source="thrown" loss="pose" evaluate="final" seed="0">
    <target position="1.2 0.0 0.05" orientation="1 0 0 0"/>
    <start-area min="{p[0] - 0.05:g} {p[1] - 0.05:g} {p[2] - 0.05:g}" max="{p[0] + 0.05:g} {p[1] + 0.05:g} {p[2] + 0.05:g}"/>
  </inference>
</scene>
"""


# ------------------------------------------------------------------ MuJoCo
def mujoco_xml(n: int) -> str:
    """The same scene in MJCF: true box geoms, DejaView's contact mapping, the step of DejaView."""
    from dejaview.io.mjcf import OPTION, contact_parameters

    contact = " ".join(f'{k}="{v}"' for k, v in contact_parameters(FRICTION, RESTITUTION).items())
    option = " ".join(f'{k}="{v}"' for k, v in OPTION.items())
    half = " ".join(f"{x / 2:g}" for x in BOX)

    def body(name, pos):
        return (f'<body name="{name}" pos="{pos[0]:g} {pos[1]:g} {pos[2]:g}"><freejoint/>'
                f'<geom type="box" size="{half}" mass="{BOX_MASS:g}"/></body>')

    bodies = [body("thrown", THROW["position"])]
    bodies += [body(f"box{i}", pos) for i, pos in enumerate(resting_positions(n - 1))]
    return f"""<mujoco model="box-across-table-{n}">
  <option timestep="{DT:g}" gravity="0 0 -9.81" {option}/>
  <default><geom {contact}/></default>
  <worldbody>
    <geom type="plane" size="0 0 1"/>
    <geom type="box" pos="0 0 {TABLE[2] / 2:g}" size="{TABLE[0] / 2:g} {TABLE[1] / 2:g} {TABLE[2] / 2:g}"/>
    {"".join(bodies)}
  </worldbody>
</mujoco>"""


class MujocoProblem:
    """The thrown box's 12 parameters -> final pose loss, in MuJoCo.

    Parameters: position (3), rotation vector (3, applied to the identity orientation),
    linear velocity (3), angular velocity (3, world frame), as DejaView's layout frees them.
    """

    def __init__(self, n: int, target=(1.2, 0.0, 0.05), steps: int = STEPS):
        import mujoco
        import numpy as np

        self.mj = mujoco
        self.model = mujoco.MjModel.from_xml_string(mujoco_xml(n))
        self.data = mujoco.MjData(self.model)
        self.steps = steps
        self.target = np.asarray(target, dtype=np.float64)
        self.x0 = np.concatenate([THROW["position"], np.zeros(3), THROW["linear"], THROW["angular"]])

    def loss(self, x) -> float:
        import numpy as np

        mj, m, d = self.mj, self.model, self.data
        mj.mj_resetData(m, d)
        q = np.zeros(4)
        mj.mju_axisAngle2Quat(q, x[3:6] / max(np.linalg.norm(x[3:6]), 1e-300), np.linalg.norm(x[3:6]))
        d.qpos[0:3] = x[0:3]
        d.qpos[3:7] = q
        rot = np.zeros(9)
        mj.mju_quat2Mat(rot, q)
        d.qvel[0:3] = x[6:9]
        d.qvel[3:6] = rot.reshape(3, 3).T @ x[9:12]  # a free joint's angular velocity: body frame
        mj.mj_step(m, d, nstep=self.steps)
        pos, quat = d.qpos[0:3], d.qpos[3:7]
        angle = 2.0 * math.acos(min(1.0, abs(float(quat[0]))))  # against the identity orientation
        return float(np.linalg.norm(pos - self.target) + ORIENTATION_WEIGHT * angle)

    def final_position(self, x):
        self.loss(x)
        return self.data.qpos[0:3].copy()

    def fd_gradient(self, x):
        """Loss and forward-difference gradient: 13 rollouts."""
        import numpy as np

        base = self.loss(x)
        grad = np.empty(len(x))
        for i in range(len(x)):
            xp = np.array(x, dtype=np.float64)
            xp[i] += FD_EPS
            grad[i] = (self.loss(xp) - base) / FD_EPS
        return base, grad


# ------------------------------------------------------------------ helpers
MIN_SECONDS = 0.3  # a timing repeats its call until this long has passed (at most MAX_RUNS runs)
MAX_RUNS = 200


def _best_time(fn, repeats: int) -> float:
    """Best of at least ``repeats`` runs, more for short calls (``MIN_SECONDS`` in all): a
    millisecond call timed 3 times moves by 20-30 % with the machine; both engines alike."""
    best = math.inf
    started = time.perf_counter()
    runs = 0
    while runs < max(1, repeats) or (time.perf_counter() - started < MIN_SECONDS and runs < MAX_RUNS):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
        runs += 1
    return best


def _ms(seconds: float) -> str:
    """Milliseconds with two decimals below 10 ms (the N = 1 race is decided by tenths)."""
    ms = 1e3 * seconds
    return f"{ms:.2f}" if ms < 10 else f"{ms:.1f}"


def _status_kib(key: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def _problem(scene_text_or_path, steps: int | None = None):
    from dataclasses import replace

    from dejaview.backends.spheres import SpheresProblem
    from dejaview.scene import Scene
    from dejaview.scene.xml import read_scene_string

    if isinstance(scene_text_or_path, Path):
        scene = Scene.from_xml(scene_text_or_path)
    else:
        scene = read_scene_string(scene_text_or_path, base_dir=ROOT / "examples" / "scenes")
    problem = SpheresProblem.from_scene(scene, engine="native")
    return replace(problem, steps=steps) if steps else problem


def _dv_timings(problem, x, repeats: int) -> tuple[float, float]:
    """(rollout seconds, loss + reverse gradient seconds) of parameters x (B, P)."""
    import torch

    def simulate():  # the loss's rollout: records what the loss reads (the end state here)
        with torch.no_grad():
            problem.simulate(x)

    simulate()
    problem.value_and_grad(x, "reverse")
    t_roll = _best_time(simulate, repeats)
    t_grad = _best_time(lambda: problem.value_and_grad(x, "reverse"), repeats)
    return t_roll, t_grad


def memory_probe(batch: int, steps: int | None = None) -> dict:
    """Peak memory a reverse-mode loss + gradient of ``batch`` mug candidates adds (MiB)."""
    import torch

    problem = _problem(MUG, steps)
    x = problem.layout.encode().to(problem.world.dtype)
    x = x + 0.01 * torch.randn(batch, x.shape[1], generator=torch.Generator().manual_seed(0), dtype=x.dtype)
    base = None
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
            fh.write("5")  # resets VmHWM to the current RSS (Linux >= 4.0)
        base = _status_kib("VmRSS")
    except OSError:
        pass
    started = time.perf_counter()
    loss, grad = problem.value_and_grad(x, "reverse")
    seconds = time.perf_counter() - started
    peak = _status_kib("VmHWM")
    finite = bool(torch.isfinite(loss).all() and torch.isfinite(grad).all())
    growth = None if base is None or peak is None else max(0, peak - base) / 1024
    return {"peak_growth_mib": growth, "seconds": seconds, "finite": finite, "batch": batch,
            "steps": problem.steps}


# ------------------------------------------------------------------ benchmark
def run(print_fn=print, quick: bool = False, counts=COUNTS, repeats: int = 3,
        memory_batch: int = 1024) -> list[dict]:
    """Run the comparison (module docstring).

    Returns:
        Rows: ``section`` boxes (n, dv_rollout_s, dv_grad_s, mj_rollout_s, mj_fd_grad_s,
        grad_over_rollout, fd_over_grad, final_offset_m), mug (batch, dv_rollout_s, dv_grad_s
        per candidate), memory (batch, peak_growth_mib, seconds) and target (name, met).
    """
    import numpy as np
    import torch

    from dejaview.cli.bench_table import load_average
    from dejaview.sim import native

    say = print_fn or (lambda *_: None)
    steps = 50 if quick else STEPS
    if quick:
        counts = tuple(c for c in counts if c <= 2) or (1,)
        repeats = 1
    native.extension()
    say(f"issue 25 peers: box thrown across a table onto the floor, {steps} steps of {DT * 1000:g} ms, "
        f"12 free parameters; torch {torch.__version__}, native engine {native.threads()} thread(s); "
        f"{load_average()}")
    rows: list[dict] = []
    say("")
    say(f"{'N':>3} {'dv rollout':>11} {'dv loss+grad':>13} {'grad/roll':>10} {'mj rollout':>11} "
        f"{'mj fd grad':>11} {'fd/dv grad':>11} {'dv-mj final':>12}")
    for n in counts:
        problem = _problem(box_scene(n, steps))
        x = problem.layout.encode().to(problem.world.dtype)
        assert problem.num_params == 12, problem.layout.names()
        t_roll, t_grad = _dv_timings(problem, x, repeats)
        mj = MujocoProblem(n, steps=steps)
        mj.fd_gradient(mj.x0)
        mj_roll = _best_time(lambda: mj.loss(mj.x0), repeats)
        mj_grad = _best_time(lambda: mj.fd_gradient(mj.x0), repeats)
        with torch.no_grad():
            final = problem.simulate(x, record_every=steps).states.position[-1, 0, problem.source]
        src_com = final.numpy()  # centre of mass (the box's origin is its centre)
        offset = float(np.linalg.norm(src_com - mj.final_position(mj.x0)))
        row = {"section": "boxes", "n": n, "steps": steps, "dv_rollout_s": t_roll, "dv_grad_s": t_grad,
               "mj_rollout_s": mj_roll, "mj_fd_grad_s": mj_grad, "grad_over_rollout": t_grad / t_roll,
               "fd_over_grad": mj_grad / t_grad, "final_offset_m": offset}
        rows.append(row)
        say(f"{n:>3} {_ms(t_roll):>9}ms {_ms(t_grad):>11}ms {t_grad / t_roll:>9.2f}x "
            f"{_ms(mj_roll):>9}ms {_ms(mj_grad):>9}ms {mj_grad / t_grad:>10.2f}x {offset:>10.3f} m")

    # ---- the mug reference scene, DejaView only
    mug = _problem(MUG, steps if quick else None)
    x1 = mug.layout.encode().to(mug.world.dtype)
    batch = 4 if quick else 64
    xb = x1 + 0.01 * torch.randn(batch, x1.shape[1], generator=torch.Generator().manual_seed(0),
                                 dtype=x1.dtype)
    say("")
    say(f"mug reference scene ({MUG.relative_to(ROOT)}, {mug.steps} steps):")
    for b, x in ((1, x1), (batch, xb)):
        t_roll, t_grad = _dv_timings(mug, x, 1 if b > 1 else repeats)
        rows.append({"section": "mug", "batch": b, "dv_rollout_s": t_roll / b, "dv_grad_s": t_grad / b,
                     "grad_over_rollout": t_grad / t_roll})
        say(f"  B = {b:>3}: rollout {1e3 * t_roll / b:8.2f} ms, loss+grad {1e3 * t_grad / b:8.2f} ms "
            f"per candidate ({t_grad / t_roll:.2f}x)")

    # ---- peak memory of a large batch
    mb = 8 if quick else memory_batch
    mem = memory_probe(mb, steps if quick else None)
    rows.append({"section": "memory", **mem})
    growth = "unknown (no /proc)" if mem["peak_growth_mib"] is None else f"{mem['peak_growth_mib']:.0f} MiB"
    say(f"  peak memory of a {mb}-candidate loss + gradient ({mem['steps']} steps): {growth} "
        f"({mem['seconds']:.1f} s{'' if mem['finite'] else ', NOT FINITE'})")

    # ---- targets
    boxes = [r for r in rows if r["section"] == "boxes"]
    targets = [
        ("exact gradient >= 3x faster than MuJoCo FD at every N",
         all(r["fd_over_grad"] >= TARGET_GRAD_SPEEDUP for r in boxes)),
        ("rollout at least as fast as MuJoCo at N = 1",
         all(r["dv_rollout_s"] <= r["mj_rollout_s"] for r in boxes if r["n"] == 1)),
        ("gradient <= 4x rollout at every N", all(r["grad_over_rollout"] <= TARGET_GRAD_OVER_ROLLOUT
                                                  for r in boxes)),
    ]
    say("")
    for name, met in targets:
        rows.append({"section": "target", "name": name, "met": met})
        say(f"  {'met ' if met else 'MISSED'} {name}")
    return rows


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--memory-batch", type=int, default=1024)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    run(quick=args.quick, repeats=args.repeats, memory_batch=args.memory_batch)
