"""Fingerprint the native engine before and after a change to its C++: states and both gradients.

    .venv/bin/python scripts/native_fingerprint.py record /tmp/before.npz   # on the old checkout
    .venv/bin/python scripts/native_fingerprint.py record /tmp/after.npz    # on the new one
    .venv/bin/python scripts/native_fingerprint.py compare /tmp/before.npz /tmp/after.npz

Run it as a file from the checkout's root with ``PYTHONPATH=.`` when the environment's
editable install points at another checkout. For each bundled scene in ``SCENES`` that the
checkout has: a batch of two initial states (the scene's and a perturbed copy), 150 steps on
the native engine recording every 10th, and a scalar loss of the recorded states; stored are
the states ``(16, 2, N, 13)``, the loss's reverse-mode gradient with respect to the initial
state ``(2, N, 13)`` and its forward-mode derivative along a fixed direction ``()``.
Each scene is fingerprinted too (``NAME/scene_sha256``, of the scene without its ``<inference>``,
as the writer writes it): ``compare`` skips a scene whose objects or simulation changed between
the two records. ``compare`` prints, per array, ``identical`` or the
largest difference, and exits 1 when any array present in both differs by more than ``--atol``
(default 0: bit for bit).

``tests/fixtures/native/fingerprint-unload-min.npz`` is the record of the engine since the
unloading factor below zero for restitutions under 0.111 (2026-12-07, ``restitution.UNLOAD_MIN``);
``tests/sim/test_native_fingerprint.py`` holds today's engine to it within 1e-9. (Before, the
records were of the engine since the loading-to-unloading blend over a part of an impact's phase,
2026-12-07, ``fingerprint-phase-blend.npz``, since the roll stick of a line contact, 2026-11-26,
``fingerprint-roll-stick.npz``, since the friction on the predicted slip, 2026-11-25,
``fingerprint-predicted-slip.npz``, and of the engine issue 25 was filed against, commit 30cf17f,
``fingerprint-30cf17f.npz``, all in the git history.)
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np
import torch

SCENES = ("mug_thrown", "box_along_shelf", "mug_off_counter", "box_among_boxes", "ball_down_ramp",
          "box_hits_arm", "box_down_ramp")
STEPS, RECORD_EVERY = 150, 10


def record(out: Path, scenes_dir: Path) -> None:
    from dejaview.scene.xml import read_scene_file
    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import rollout
    from dejaview.sim.state import State
    from dejaview.sim.world import World

    arrays = {}
    for name in SCENES:
        path = scenes_dir / f"{name}.xml"
        if not path.exists():
            continue
        scene = read_scene_file(path)
        physics = scene.replace(inference=None).to_xml().encode()  # what the rollouts read, not the targets
        arrays[f"{name}/scene_sha256"] = np.array(hashlib.sha256(physics).hexdigest())
        world = World.from_scene(scene)
        x0 = initial_state(world, scene, batch_size=2).flat()  # (2, N, STATE_WIDTH)
        x0[1] += 0.01 * torch.randn(x0[1].shape, generator=torch.Generator().manual_seed(1), dtype=x0.dtype)

        def run(x):
            traj = rollout(world, State.from_flat(x), steps=STEPS,
                           record_every=RECORD_EVERY, engine="native")
            s = traj.states
            loss = (s.position ** 2).sum() + (s.linear_velocity ** 2).sum() + (s.orientation[..., 1:] ** 2).sum()
            return traj, loss

        with torch.no_grad():
            traj, _ = run(x0)
        arrays[f"{name}/states"] = traj.states.flat().numpy()
        x = x0.clone().requires_grad_(True)
        arrays[f"{name}/reverse"] = torch.autograd.grad(run(x)[1], x)[0].numpy()
        v = torch.randn(x0.shape, generator=torch.Generator().manual_seed(0), dtype=x0.dtype)
        arrays[f"{name}/forward"] = torch.func.jvp(lambda y: run(y)[1], (x0,), (v,))[1].numpy()
    np.savez(out, **arrays)
    print(f"wrote {len(arrays)} arrays to {out}")


def differences(before: Path, after: Path) -> dict[str, float | None]:
    """Per array of ``before``: the largest difference to ``after`` (0.0 when bit for bit equal;
    inf when the shapes differ; None when ``after`` lacks it or the scene's XML changed)."""
    a, b = np.load(before), np.load(after)
    out: dict[str, float | None] = {}
    for key in a.files:
        if key.endswith("/scene_sha256"):
            continue
        sha = key.split("/")[0] + "/scene_sha256"
        changed = sha in a.files and sha in b.files and str(a[sha]) != str(b[sha])
        if key not in b.files or changed:
            out[key] = None
        elif a[key].shape != b[key].shape:
            out[key] = float("inf")
        else:
            out[key] = float(np.abs(a[key] - b[key]).max())
    return out


def compare(before: Path, after: Path, atol: float) -> int:
    diffs = differences(before, after)
    shapes = np.load(before)
    for key, diff in diffs.items():
        if diff is None:
            print(f"{key}: not compared (missing from {after}, or the scene changed)")
        else:
            print(f"{key} {shapes[key].shape}: " + ("identical" if diff == 0 else f"max diff {diff:.3g}"))
    for key in sorted(set(np.load(after).files) - set(shapes.files)):
        print(f"{key}: only in {after}")
    worst = max((d for d in diffs.values() if d is not None), default=0.0)
    return 0 if worst <= atol else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("out", type=Path)
    rec.add_argument("--scenes", type=Path, default=Path("examples/scenes"))
    cmp = sub.add_parser("compare")
    cmp.add_argument("before", type=Path)
    cmp.add_argument("after", type=Path)
    cmp.add_argument("--atol", type=float, default=0.0)
    args = parser.parse_args(argv)
    if args.command == "record":
        record(args.out, args.scenes)
        return 0
    return compare(args.before, args.after, args.atol)


if __name__ == "__main__":
    sys.exit(main())
