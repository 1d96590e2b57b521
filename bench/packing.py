"""Sphere packing benchmark.

    python bench/packing.py

Packs the example box, ball and mug and a generated 10 000-triangle mesh into
at most 256 spheres and prints, for each: sphere count, coverage of the volume,
how far the spheres reach outside the mesh, and the build time. Targets:

* coverage >= 80 % with <= 256 spheres for box, ball and mug;
* no sphere more than 2 mm outside its mesh;
* the 10 000-triangle mesh packed into 256 spheres in under 15 s.

``run(print_fn=print)`` returns the rows as dicts (for ``dejaview bench packing``).
"""

from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MESHES = ROOT / "examples" / "meshes"

MAX_SPHERES = 256
MIN_COVERAGE = 0.80
MAX_OUTSIDE = 0.002  # metres
MAX_SECONDS_10K = 15.0


def _test_mesh():
    """The generated 10 000-triangle mesh from examples/build_meshes.py."""
    spec = importlib.util.spec_from_file_location("build_meshes", ROOT / "examples" / "build_meshes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.test_mesh(faces=10_000)


def run(print_fn=print, max_spheres: int = MAX_SPHERES) -> list[dict]:
    """Run the benchmark.

    Args:
        print_fn: where the table and the verdict go (None: silent).
        max_spheres: sphere budget for every mesh.
    Returns:
        One dict per mesh: name, triangles, spheres, coverage (0..1),
        max_outside_mm, seconds (build time), ok (targets met), and the summary
        {"name": "all", "ok": ...} last.
    """
    sys.path.insert(0, str(ROOT))
    from dejaview.geometry.mesh import load_mesh
    from dejaview.geometry.packing import SpherePacking

    say = print_fn or (lambda *_: None)
    cases = [(name, lambda name=name: load_mesh(MESHES / f"{name}.obj"))
             for name in ("box", "ball", "mug")]
    cases.append(("10k triangles", _test_mesh))
    rows = []
    say(f"{'mesh':<14} {'triangles':>9} {'spheres':>7} {'coverage':>9} "
        f"{'max outside':>12} {'seconds':>8}  targets")
    for name, make in cases:
        mesh = make()
        started = time.perf_counter()
        packing = SpherePacking.from_mesh(mesh, max_spheres=max_spheres)
        seconds = time.perf_counter() - started
        quality = packing.quality(mesh)
        ok = quality.count <= max_spheres and quality.max_outside <= MAX_OUTSIDE
        if name == "10k triangles":
            ok = ok and seconds < MAX_SECONDS_10K
        else:
            ok = ok and quality.coverage >= MIN_COVERAGE
        row = {
            "name": name,
            "triangles": int(len(mesh.faces)),
            "spheres": quality.count,
            "coverage": quality.coverage,
            "max_outside_mm": 1000.0 * quality.max_outside,
            "seconds": seconds,
            "ok": bool(ok),
        }
        rows.append(row)
        say(f"{name:<14} {row['triangles']:>9} {row['spheres']:>7} "
            f"{100 * row['coverage']:>8.1f}% {row['max_outside_mm']:>9.2f} mm "
            f"{seconds:>8.2f}  {'met' if ok else 'MISSED'}")
    every = all(row["ok"] for row in rows)
    say(f"targets: coverage >= {100 * MIN_COVERAGE:.0f}% with <= {max_spheres} spheres "
        f"(box, ball, mug); max outside <= {1000 * MAX_OUTSIDE:.0f} mm; 10k triangles "
        f"< {MAX_SECONDS_10K:.0f} s: {'all met' if every else 'NOT all met'}")
    rows.append({"name": "all", "ok": every})
    return rows


if __name__ == "__main__":
    sys.exit(0 if run()[-1]["ok"] else 1)
