"""Physically meaningful ranges of the numbers in a scene, and the step budget of a simulation.

A scene may be valid XML with finite numbers and still be absurd: a ball at 1e200 m/s, a mass of
1e300 kg, gravity of 1e300 m/s^2, ``dt="1e-300"`` (1e300 steps). The reader
(:mod:`dejaview.scene.validate`) refuses them with a one-line error naming the element, so that
``dejaview validate`` says everything ``dejaview simulate`` would refuse. The ranges are generous
(far beyond any rigid-body scene on a table, a shelf or a floor) and keep every product the
simulator forms (masses times lengths squared, speeds times steps) far from overflow.

What the simulation then does with sane inputs is watched by the divergence check
(:mod:`dejaview.sim.divergence`): a state that turns non-finite or leaves ``DIVERGED_*`` ends a
forward simulation with an error naming the object, the step and the quantity.

No torch here: the scene package stays light.
"""

from __future__ import annotations

import math

MAX_STEPS = 2_000_000
"""Step budget of one simulation: integration steps (steps x substeps), e.g. 1,000,000 steps of
dt at the default 2 substeps. The environment variable ``DEJAVIEW_MAX_STEPS`` changes it
everywhere (``max_steps()``); ``simulate(max_steps=)``, ``dejaview simulate --max-steps`` and
``dejaview validate --max-steps`` for one run."""

MAX_LENGTH = 1e4
"""m: largest |coordinate| of a position (poses, targets, start area) and largest size."""
MIN_SIZE = 1e-4
"""m: smallest box side, radius or height of a primitive (0.1 mm)."""
MAX_SPEED = 1e4
"""m/s: largest initial or target linear speed (and contact unload-velocity)."""
MAX_SPIN = 1e4
"""rad/s: largest initial or target angular speed."""
MAX_GRAVITY = 1e3
"""m/s^2: largest gravity (about 100 g)."""
MIN_MASS, MAX_MASS = 1e-6, 1e9
"""kg: range of an object's mass (given or from its density and volume)."""
MIN_DENSITY, MAX_DENSITY = 1e-3, 1e6
"""kg/m^3: range of a density."""
MAX_FRICTION = 10.0
"""Largest Coulomb friction coefficient."""
MAX_DT = 1.0
"""s: longest step (no contact is resolved with steps of seconds)."""
MAX_SUBSTEPS = 1000
"""Most integration substeps per step."""
MAX_CONTACT_OMEGA_H = 2.0
"""Largest contact-frequency x substep: semi-implicit Euler of a spring is unstable beyond 2."""
MIN_SDF_SPACING = 1e-4
"""m: finest signed distance grid spacing."""
MAX_CONTACTS = 1_000_000_000
"""Largest contact capacity (max-static-contacts, max-pair-contacts): in effect no cap; the native
engine holds it in a C int."""
MAX_PENALTY_WEIGHT = 1e6
"""Largest penalty weight."""
MAX_ITERATIONS = 1_000_000
"""Most optimiser iterations a scene may ask for."""
MAX_HEATMAP_CELLS = 1024
"""Most heatmap cells along one axis."""
MAX_HEATMAP_SAMPLES = 1024
"""Most initial guesses per heatmap cell."""
MAX_POSTERIOR_SAMPLES = 1_000_000
"""Most posterior samples a solve may draw."""
MAX_RELATIVE_UNCERTAINTY = 1.0
"""Largest relative standard deviation of a physics parameter in ``<model-uncertainty>`` (100 %)."""
MAX_PHYSICS_PRIOR_SD = 10.0
"""Largest relative standard deviation in ``<physics-prior>`` (a log-normal's: 10 spans e^10)."""
MAX_SEED = 2 ** 63 - 1
"""Largest random seed (torch takes 64-bit seeds)."""

DEFAULT_SUBSTEPS = 2
"""The sphere simulator's substeps per step when ``<simulation substeps>`` is absent ..."""
BOX_BODY_SUBSTEPS = 4
"""... and in a scene with a movable box, whose 8 corners meet planes and static boxes
(``dejaview.sim.box_edges``), at the same contact frequency (``dejaview.sim.build.step_settings``):
a corner takes an impact at one point, where a packing spreads it over spheres that engage one
after another, and at 2 substeps (omega_0 h = 0.25) where in its substep the contact begins moves
the end by millimetres per 1e-7 of the start; L-BFGS stalls on that (docs/physics.md, "Steps")."""


def default_substeps(scene) -> int:
    """Substeps per step of ``scene`` when its ``<simulation>`` does not say: ``BOX_BODY_SUBSTEPS``
    where a movable object is a box primitive, else ``DEFAULT_SUBSTEPS``."""
    boxes = any(not o.fixed and o.mesh is None and o.robot is None and o.shape == "box"
                for o in scene.objects)
    return BOX_BODY_SUBSTEPS if boxes else DEFAULT_SUBSTEPS

# <simulation> attributes of the sphere simulator: name -> (type, minimum, maximum)
SIM_EXTRAS = {
    "substeps": (int, 1, MAX_SUBSTEPS),
    "contact-frequency": (float, 0.0, math.inf),  # bounded through MAX_CONTACT_OMEGA_H
    "unload-velocity": (float, 0.0, MAX_SPEED),
    "sdf-spacing": (float, MIN_SDF_SPACING, MAX_LENGTH),
    "max-static-contacts": (int, 1, MAX_CONTACTS),
    "max-pair-contacts": (int, 1, MAX_CONTACTS),
}


def max_steps(value: int | None = None) -> int:
    """``value`` if given, else ``DEJAVIEW_MAX_STEPS`` if set, else ``MAX_STEPS``.

    Raises:
        DejaViewError: a budget that is not a positive integer.
    """
    import os

    from dejaview.errors import DejaViewError

    where = "max_steps"
    if value is None:
        text = os.environ.get("DEJAVIEW_MAX_STEPS")
        if not text:
            return MAX_STEPS
        where = "DEJAVIEW_MAX_STEPS"
        try:
            value = int(text)
        except ValueError:
            raise DejaViewError(f"DEJAVIEW_MAX_STEPS must be a positive integer, got {text!r}") from None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise DejaViewError(f"{where} must be a positive integer, got {value!r}")
    return value


def parse_extra(name: str, text) -> tuple[object, str | None]:
    """``(value, None)`` for a valid ``<simulation name=text>`` of ``SIM_EXTRAS``, else
    ``(None, reason)``."""
    kind, lo, hi = SIM_EXTRAS[name]
    what = "an integer" if kind is int else "a number"
    try:
        value = kind(str(text).strip())
    except (ValueError, OverflowError):
        return None, f"simulation attribute {name}={text!r} is not {what}"
    if kind is float and not math.isfinite(value):
        return None, f"simulation attribute {name}={text!r} is not finite"
    too_small = value <= lo if lo == 0 else value < lo
    if too_small:
        bound = "positive" if lo == 0 else f"at least {lo:g}"
        return None, f"simulation attribute {name}={text!r} must be {bound}"
    if value > hi:
        return None, f"simulation attribute {name}={text!r} is over the limit of {hi:g}"
    return value, None


def step_count(duration: float, dt: float) -> float:
    """``duration / dt`` rounded, at least 1, as a float (``inf`` where it overflows)."""
    ratio = duration / dt
    if not math.isfinite(ratio):
        return math.inf
    return float(max(1, round(ratio)))


def budget_problem(steps: float, substeps: int, max_steps: int, what: str) -> str | None:
    """The one-line reason why ``steps`` x ``substeps`` is over ``max_steps``, or None."""
    total = steps * substeps
    if total <= max_steps:
        return None

    def count(x: float) -> str:
        return str(int(x)) if x < 1e12 else f"{x:.4g}"

    per = f" x {substeps} substeps" if substeps != 1 else ""
    return (f"{what} is {count(steps)} steps{per} = {count(total)} integration steps, over the budget of "
            f"{max_steps} (raise it with --max-steps or DEJAVIEW_MAX_STEPS)")
