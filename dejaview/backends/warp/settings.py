"""Settings of the ``warp`` backend: the ``warp-*`` attributes of ``<simulation>``, overridden by
options of ``make_problem(scene, "warp", ...)``.

- ``warp-integrator``: ``xpbd`` (default, as in the original work: ``wp.sim.XPBDIntegrator``, no
  torsional or rolling friction) | ``semi-implicit`` (``wp.sim.SemiImplicitIntegrator``: penalty
  contacts whose stiffness is set from the lightest body, ``k = m (0.1 / h)^2``, damping from the
  scene's restitution, Warp's smoothed Coulomb friction);
- ``warp-substeps``: integrator substeps per step (default 1 for XPBD, 10 for semi-implicit,
  whose explicit contacts need a substep of a fraction of a millisecond); contacts are generated
  once per step (``wp.sim.collide``) with a 5 cm margin;
- ``warp-iterations`` (default 2): XPBD constraint iterations;
- ``warp-restitution`` (``true`` | ``false``, default false): XPBD's restitution pass. Off by
  default, so XPBD contacts are inelastic whatever the scene's restitution: in Warp 1.9.1 that
  pass breaks reverse mode (``docs/engines.md``, "The Warp backend").

This module does not import Warp.
"""

from __future__ import annotations

from dejaview.errors import InferenceError, SceneError

INTEGRATORS = ("xpbd", "semi-implicit")
SIM_EXTRAS = {"warp-integrator": str, "warp-substeps": int, "warp-iterations": int, "warp-restitution": bool}
CONTACT_MARGIN = 0.05  # m; speculative contacts found once per step must cover a step's motion
DEFAULT_SUBSTEPS = {"xpbd": 1, "semi-implicit": 10}
SEMI_IMPLICIT_OMEGA_H = 0.1  # contact frequency x substep of the semi-implicit penalty contacts


def override_problem(name: str, value) -> str | None:
    """Why an override of ``make_problem(scene, "warp", ...)`` cannot run, or None: ``integrator``
    one of ``INTEGRATORS``, ``substeps`` and ``iterations`` positive integers."""
    if name == "integrator" and value not in INTEGRATORS:
        return f"unknown warp integrator {value!r}; choose one of {', '.join(INTEGRATORS)}"
    if name in ("substeps", "iterations") and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
        return f"warp {name} must be a positive integer, got {value!r}"
    return None


def warp_settings(scene, integrator: str | None = None, substeps: int | None = None,
                  iterations: int | None = None, restitution: bool | None = None) -> dict:
    """The backend attributes of ``<simulation>`` (module docstring), overridden by options.

    Returns:
        {"integrator", "substeps", "iterations", "restitution"}.
    Raises:
        SceneError: a bad attribute value; InferenceError: a bad option.
    """
    where = dict(file=str(scene.path) if scene.path else None, element="simulation")
    extra = scene.simulation.extra
    out = {"integrator": "xpbd", "substeps": None, "iterations": 2, "restitution": False}
    for key, kind in SIM_EXTRAS.items():
        if key not in extra:
            continue
        text = extra[key]
        name = key.removeprefix("warp-")
        if kind is bool:
            if text not in ("true", "false"):
                raise SceneError(f"simulation attribute {key}={text!r} must be true or false", **where)
            out[name] = text == "true"
            continue
        if kind is str:
            if text not in INTEGRATORS:
                raise SceneError(f"simulation attribute {key}={text!r}: choose one of {', '.join(INTEGRATORS)}",
                                 **where)
            out[name] = text
            continue
        try:
            value = int(text)
        except ValueError:
            value = 0
        if value < 1:
            raise SceneError(f"simulation attribute {key}={text!r} must be a positive integer", **where)
        out[name] = value
    for name, value in (("integrator", integrator), ("substeps", substeps), ("iterations", iterations),
                        ("restitution", restitution)):
        if value is None:
            continue
        if name == "restitution":
            out[name] = bool(value)
            continue
        reason = override_problem(name, value)
        if reason:
            raise InferenceError(reason)
        out[name] = value
    if out["substeps"] is None:
        out["substeps"] = DEFAULT_SUBSTEPS[out["integrator"]]
    return out
