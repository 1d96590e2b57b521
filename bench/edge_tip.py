"""A rigid reference for a box sliding off a table's edge: who tips it right?

    python bench/edge_tip.py [--friction 0.5] [--speed 3.0]

The fidelity table's "box slides off the table" (``bench/crossengine.py``) has
DejaView and MuJoCo part because the box tips over the table's edge at
different rates. This is a third opinion that shares no code with either
engine: the same box (0.2 x 0.1 m side view, 1 kg) in 2D (x, z, pitch), a
flat bottom face, the table's sharp edge, stiff penalty contacts (1e6 N/m per
metre of depth, 2e3 N s/m) with Coulomb friction, explicit integration at
2 us. Contacts: the box's two bottom corners against the table top while they
are over it, and the table's edge against the box's bottom face while the edge
is under it (normal: the face's). Printed: x, z, pitch (nose down, degrees) and
pitch rate at 0.2, 0.25, 0.3, 0.35 and 0.5 s, for ``crossengine`` to compare.

``edge_impact``: the same box landing on its front edge on a floor, as one
rigid impulse (Newton's restitution, Coulomb friction): how fast it turns on
after the impact, which the fidelity rows of tumbling boxes hang on.
"""

from __future__ import annotations

import argparse
import math

LENGTH, HEIGHT, MASS = 0.2, 0.1, 1.0
TABLE_TOP, TABLE_EDGE = 0.7, 0.4
GRAVITY = 9.81
STIFFNESS, DAMPING = 1e6, 2e3
SLIP = 1e-3
"""m/s: friction is mu N v / sqrt(v^2 + SLIP^2), Coulomb above a few mm/s."""
TIMES = (0.2, 0.25, 0.3, 0.35, 0.5)


def tip(friction: float = 0.5, speed: float = 3.0, dt: float = 2e-6, times=TIMES, length: float = LENGTH,
        edge: float = TABLE_EDGE) -> dict:
    """Slide the box off the edge from rest on the table top, centre at x = 0.

    Args:
        friction: Coulomb coefficient of every contact.
        speed: m/s along +x at t = 0.
        dt: seconds per step.
        times: seconds to record.
        length: the box's extent along the slide (m; 0.15 for the box sliding across its width).
        edge: where the table ends (m from the box's start; 0.3 off the table's side).
    Returns:
        {t: (x, z, pitch in degrees, pitch rate in degrees per second)}; pitch is the rotation
        about +y (nose down positive), as ``2 atan2(q_y, q_w)`` of the 3D engines.
    """
    inertia = MASS * (length ** 2 + HEIGHT ** 2) / 12
    x, z, pitch = 0.0, TABLE_TOP + HEIGHT / 2, 0.0
    vx, vz, w = speed, 0.0, 0.0
    marks = {round(t / dt): t for t in times}
    out = {}
    for step in range(max(marks) + 1):
        if step in marks:
            out[marks[step]] = (x, z, math.degrees(pitch), math.degrees(w))
        c, s = math.cos(pitch), math.sin(pitch)
        fx, fz, torque = 0.0, -MASS * GRAVITY, 0.0

        def push(px, pz, nx, nz, depth):
            """Penalty and friction force on the box at world point (px, pz), normal (nx, nz)."""
            nonlocal fx, fz, torque
            rx, rz = px - x, pz - z
            ux, uz = vx + w * rz, vz - w * rx  # the box's velocity there (omega about +y)
            fn = max(0.0, STIFFNESS * depth - DAMPING * (ux * nx + uz * nz))
            tx, tz = nz, -nx
            vt = ux * tx + uz * tz
            ft = -friction * fn * vt / math.sqrt(vt * vt + SLIP * SLIP)
            gx, gz = fn * nx + ft * tx, fn * nz + ft * tz
            fx, fz = fx + gx, fz + gz
            torque += rz * gx - rx * gz

        for bx in (-length / 2, length / 2):  # bottom corners on the table top
            px, pz = x + c * bx - s * HEIGHT / 2, z - s * bx - c * HEIGHT / 2
            if px <= edge and pz < TABLE_TOP:
                push(px, pz, 0.0, 1.0, TABLE_TOP - pz)
        ex, ez = edge - x, TABLE_TOP - z  # the edge in the box's frame
        bx, bz = c * ex - s * ez, s * ex + c * ez
        if abs(bx) < length / 2 and -HEIGHT / 2 < bz < 0:  # under the bottom face, inside the box
            push(edge, TABLE_TOP, s, c, bz + HEIGHT / 2)
        vx, vz, w = vx + dt * fx / MASS, vz + dt * fz / MASS, w + dt * torque / inertia
        x, z, pitch = x + dt * vx, z + dt * vz, pitch + dt * w
    return out


def edge_impact(pitch: float, velocity, pitch_rate: float, restitution: float = 0.3,
                friction: float = 0.5) -> tuple[float, float, float]:
    """A rigid impact of the box (side view, 1 kg) on its front-bottom edge on a floor.

    The box, pitched nose down by ``pitch`` degrees (its lowest point the front-bottom edge),
    moving at ``velocity`` (vx, vz) m/s and turning at ``pitch_rate`` degrees per second, meets
    the floor at that edge: one instantaneous impulse with Newton's restitution on the edge's
    normal speed and Coulomb friction (the edge sticks where the impulse that stops its slip
    needs at most ``friction`` times the normal impulse, else it slides with the largest).
    Where the edge sticks, Poisson's and Stronge's restitution give the same impulse.

    Returns:
        (vx, vz, pitch rate in degrees per second) just after the impact.
    """
    m, inertia = MASS, MASS * (LENGTH ** 2 + HEIGHT ** 2) / 12.0
    th = math.radians(pitch)
    c, s = math.cos(th), math.sin(th)
    rx = c * LENGTH / 2 - s * HEIGHT / 2  # the edge from the centre of mass (x, z)
    rz = -s * LENGTH / 2 - c * HEIGHT / 2
    w = math.radians(pitch_rate)
    vx, vz = float(velocity[0]), float(velocity[1])

    def after(px: float, pz: float) -> tuple[float, float, float]:
        w1 = w + (rz * px - rx * pz) / inertia
        return vx + px / m, vz + pz / m, w1

    def edge_velocity(v: tuple[float, float, float]) -> tuple[float, float]:
        return v[0] + v[2] * rz, v[1] - v[2] * rx

    u0 = edge_velocity((vx, vz, w))
    # the edge's velocity change per unit impulse (a 2 x 2 matrix, columns: px, pz)
    k = [[edge_velocity(after(*e))[i] - u0[i] for e in ((1.0, 0.0), (0.0, 1.0))] for i in range(2)]
    target = (0.0, -restitution * u0[1])
    det = k[0][0] * k[1][1] - k[0][1] * k[1][0]
    b = (target[0] - u0[0], target[1] - u0[1])
    px, pz = (b[0] * k[1][1] - k[0][1] * b[1]) / det, (k[0][0] * b[1] - k[1][0] * b[0]) / det
    if abs(px) > friction * pz:  # it slides: the friction impulse at its bound, against the slip
        d = -math.copysign(friction, u0[0])
        pz = b[1] / (k[1][0] * d + k[1][1])
        px = d * pz
    v = after(px, pz)
    return v[0], v[1], math.degrees(v[2])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--friction", type=float, default=0.5)
    parser.add_argument("--speed", type=float, default=3.0)
    args = parser.parse_args(argv)
    for t, (x, z, pitch, rate) in tip(args.friction, args.speed).items():
        print(f"{t:5.2f} s  x {x:.3f}  z {z:.3f}  pitch {pitch:6.1f} deg  rate {rate:6.1f} deg/s")


if __name__ == "__main__":
    main()
