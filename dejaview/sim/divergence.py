"""The divergence check of forward simulations: never a NaN in an output file.

A forward simulation (``dejaview.sim.simulate``: ``dejaview simulate``, a server's simulate job,
the trajectory a solve writes) ends with a one-line ``SimulationError`` naming the object, the step
and the quantity as soon as a body's state turns non-finite or leaves the sane range:

- position: a coordinate beyond ``DIVERGED_REACH``;
- orientation: a non-finite quaternion;
- linear velocity: faster than ``DIVERGED_SPEED`` (light: a Newtonian rigid body is no longer one);
- angular velocity: a surface speed (|w| times the body's bounding radius) faster than that.

Both engines check every step: the torch engine here (``check``), the native one in C++
(``native/recording.h``'s ``diverged``, given ``native_limits()``), a few comparisons per body and
step. Batched loss evaluation (inference, heatmaps) does not check: a candidate that diverges
there gets a non-finite loss, which the optimisers treat as a bad candidate while the others go on.
"""

from __future__ import annotations

import torch

from dejaview.errors import SimulationError
from dejaview.sim.state import state_offsets

DIVERGED_REACH = 1e12
"""m: a coordinate beyond this is a diverged simulation."""
DIVERGED_SPEED = 299_792_458.0
"""m/s: a body (or a point of its surface) faster than light is a diverged simulation."""

QUANTITIES = ("position", "orientation", "linear velocity", "angular velocity")
"""The parts of a body's state, in ``STATE_LAYOUT`` order (a quantity's index is its part's)."""


def native_limits() -> list[float]:
    """The limits as ``rollout.cpp`` reads them after its other floats."""
    return [DIVERGED_REACH, DIVERGED_SPEED]


def describe(world, step: int, body: int, quantity: int, row: torch.Tensor) -> SimulationError:
    """The error for ``body`` whose ``quantity`` (index into ``QUANTITIES``) diverged at ``step``.

    Args:
        world: the World simulated.
        step: the step (1-based) after which the state diverged.
        body, quantity: which body and which part of its state.
        row: (STATE_WIDTH,) that body's flat state (``STATE_LAYOUT``).
    """
    first, width = list(state_offsets().values())[quantity]
    part = row.detach().double().cpu()[first:first + width]
    name = world.names[body]
    where = f"at step {step} (t = {step * world.dt:.6g} s)"
    if not torch.isfinite(part).all():
        what = f"is not finite ({', '.join(f'{float(v):.4g}' for v in part)})"
    elif quantity == 0:
        what = f"reached {float(part.abs().max()):.4g} m, beyond {DIVERGED_REACH:g} m"
    elif quantity == 2:
        what = f"reached {float(part.norm()):.4g} m/s, beyond {DIVERGED_SPEED:g} m/s"
    else:
        bound = float(world.bound[body])
        what = (f"reached {float(part.norm()):.4g} rad/s (surface speed {float(part.norm()) * bound:.4g} m/s, "
                f"beyond {DIVERGED_SPEED:g} m/s)")
    return SimulationError(f"the simulation diverged {where}: object {name!r} {QUANTITIES[quantity]} {what}")


def check(world, state, step: int) -> None:
    """Raise the error of ``describe`` for the first diverged body of ``state`` (B, N, ...), if any.

    Raises:
        SimulationError: a body's state is non-finite or out of range.
    """
    x, q, v, w = (t.detach() for t in state.tensors())
    bound = world.bound.to(w.dtype)
    bad = torch.stack([
        ~(x.abs() <= DIVERGED_REACH).all(-1),
        ~torch.isfinite(q).all(-1),
        ~(torch.linalg.vector_norm(v, dim=-1) <= DIVERGED_SPEED),
        ~(torch.linalg.vector_norm(w, dim=-1) * bound <= DIVERGED_SPEED),
    ], -1)  # (B, N, 4)
    if not bool(bad.any()):
        return
    b, n, k = (int(i) for i in bad.nonzero()[0])
    raise describe(world, step, n, k, torch.cat([x[b, n], q[b, n], v[b, n], w[b, n]]))
