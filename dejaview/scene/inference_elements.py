"""One table of the children of ``<inference>``: the reader, the writer and the validator walk it.

Each ``Element`` names its tag, the ``InferenceSettings`` field that holds it, the dataclass it
becomes and its attributes; each ``Attribute`` its XML name, the dataclass field, how it is
written (``kind``) and, for a plain number, the range the validator holds it to (``check``:
keyword arguments of ``Validator.number`` or, for an integer, ``(minimum, maximum)``). An element
or attribute added here is read, written and checked alike (``dejaview.scene.xml``,
``dejaview.scene.writer``, ``dejaview.scene.validate``); what only one of them does with it (the
targets' several-at-once rules, a start area's min below its max, a penalty's object ids) stays in
that module.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, fields

from dejaview.scene import bounds as B
from dejaview.scene.model import (Exploration, HeatmapSettings, ModelUncertainty, Observation, Optimize, Penalty,
                                  PhysicsPrior, PosteriorRequest, Prior, StartArea, Target)

KINDS = ("vector", "quat", "float", "int", "bool", "cells", "ids")
"""How an attribute is spelled: 3 numbers, a quaternion (4, normalised on reading), one number, one
integer, a boolean, 2 integers, 2 object ids."""


@dataclass(frozen=True)
class Attribute:
    xml: str
    field: str
    kind: str
    check: dict | tuple | None = None


@dataclass(frozen=True)
class Element:
    """``repeated``: the field holds a tuple of them (file order); else one or None (``Optimize``:
    its defaults when absent, written only where it differs)."""

    tag: str
    field: str
    cls: type
    attributes: tuple[Attribute, ...]
    repeated: bool = False

    def default(self, attribute: Attribute):
        """The dataclass's default of an attribute left out (None where it has none)."""
        f = {f.name: f for f in fields(self.cls)}[attribute.field]
        return None if f.default is MISSING else f.default


_POSITIVE = {"positive": True, "optional": True}

INFERENCE_ELEMENTS = (
    Element("target", "targets", Target, (
        Attribute("position", "position", "vector"),
        Attribute("orientation", "orientation", "quat"),
        Attribute("linear-velocity", "linear_velocity", "vector"),
        Attribute("angular-velocity", "angular_velocity", "vector"),
        Attribute("time", "time", "float"),
        Attribute("moving", "moving", "bool"),
    ), repeated=True),
    Element("optimize", "optimize", Optimize, (
        Attribute("position", "position", "bool"),
        Attribute("orientation", "orientation", "bool"),
        Attribute("linear-velocity", "linear_velocity", "bool"),
        Attribute("angular-velocity", "angular_velocity", "bool"),
    )),
    Element("start-area", "start_area", StartArea, (
        Attribute("min", "min", "vector"),
        Attribute("max", "max", "vector"),
    )),
    Element("exploration", "exploration", Exploration, (
        Attribute("epsilon", "epsilon", "float", {"unit_interval": True}),
        Attribute("patience", "patience", "int", (1, B.MAX_ITERATIONS)),
    )),
    Element("penalty", "penalties", Penalty, (
        Attribute("between", "between", "ids"),
        Attribute("weight", "weight", "float", {"nonnegative": True, "limit": B.MAX_PENALTY_WEIGHT}),
    ), repeated=True),
    Element("heatmap", "heatmap", HeatmapSettings, (
        Attribute("cells", "cells", "cells"),
        Attribute("samples", "samples", "int"),
        Attribute("sigma", "sigma", "float"),
    )),
    Element("prior", "prior", Prior, (
        Attribute("speed", "speed", "float", _POSITIVE),
        Attribute("spin", "spin", "float", _POSITIVE),
        Attribute("tilt", "tilt", "float", _POSITIVE),
    )),
    Element("observation", "observation", Observation, (
        Attribute("sigma", "sigma", "float", _POSITIVE),
        Attribute("angle-sigma", "angle_sigma", "float", _POSITIVE),
        Attribute("rest-speed", "rest_speed", "float", _POSITIVE),
        Attribute("rest-spin", "rest_spin", "float", _POSITIVE),
    )),
    Element("model-uncertainty", "model_uncertainty", ModelUncertainty, (
        Attribute("friction", "friction", "float",
                  {"nonnegative": True, "optional": True, "limit": B.MAX_RELATIVE_UNCERTAINTY}),
        Attribute("restitution", "restitution", "float",
                  {"nonnegative": True, "optional": True, "limit": B.MAX_RELATIVE_UNCERTAINTY}),
    )),
    Element("physics-prior", "physics_prior", PhysicsPrior, tuple(
        Attribute(name, name, "float", {"nonnegative": True, "optional": True, "limit": B.MAX_PHYSICS_PRIOR_SD})
        for name in ("friction", "restitution", "stiffness"))),
    Element("posterior", "posterior", PosteriorRequest, (
        Attribute("samples", "samples", "int", (0, B.MAX_POSTERIOR_SAMPLES)),
    )),
)
"""The children of ``<inference>``, in the order they are written."""

