"""The small numbers that keep the model's formulas finite, for both engines.

The torch engine (``contacts``, ``line_contact``, ``sdf``, ``rotation``) imports them from here,
and the native engine reads the same values from ``schema.h``, which
``dejaview.sim.native.schema`` generates from this module: one change here changes both.
"""

from __future__ import annotations

import torch

TINY = 1e-30
"""Added under a square root or to a denominator that may be 0 (a slip speed, a friction scale,
a contact set's spread): finite values and derivatives there, far below any quantity it guards."""

NORMAL_EPS2 = 1e-24
"""m^2: added to a squared length under its root when normalising: a vector shorter than about
1e-12 m has no direction (two spheres' centre-to-centre vector, a shape's outward direction)."""

GRID_OUTSIDE = 1e-9
"""m: a point farther than this outside a grid's box takes the direction to the box as its
normal, nearer ones the grid's own gradient."""

SMALL_ANGLE_F64 = 1e-4
"""rad: below this angle ``rotvec_to_quat`` uses its series (float64): exact derivatives at 0."""

SMALL_ANGLE_F32 = 1e-2
"""rad: ``SMALL_ANGLE_F64`` for float32."""


def small_angle(dtype: torch.dtype) -> float:
    """The series threshold of ``rotvec_to_quat`` for ``dtype``."""
    return SMALL_ANGLE_F64 if dtype == torch.float64 else SMALL_ANGLE_F32
