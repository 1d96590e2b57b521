"""Writing scene XML (format version 1): ``scene_to_xml``, the inverse of
:mod:`dejaview.scene.xml`'s reader (a written scene reads back equal)."""

from __future__ import annotations

from lxml import etree

from dejaview.errors import SceneError
from dejaview.scene.inference_elements import INFERENCE_ELEMENTS
from dejaview.scene.model import InferenceSettings, Optimize, Scene, SceneObject, Velocity


def _default(cls, name: str):
    """The default value of dataclass field ``name`` (the model is the one place for it)."""
    return cls.__dataclass_fields__[name].default


def scene_to_xml(scene: Scene) -> str:
    """The scene as XML text, UTF-8 declaration included.

    Floats are written with ``repr`` so they read back exactly; ``version``,
    ``gravity``, every ``<simulation>`` setting, poses and the inference
    attributes are always written, other optional attributes only when set
    (or, for booleans and velocities, when not the default).

    Raises:
        SceneError: if a string of the scene cannot be written as XML.
    """
    try:
        root = _scene_element(scene)
    except (ValueError, TypeError) as exc:
        raise SceneError(f"cannot write scene as XML: {exc}",
                         str(scene.path) if scene.path else "<scene>") from None
    return etree.tostring(root, pretty_print=True, xml_declaration=True,
                          encoding="UTF-8").decode("utf-8")



def _f(x) -> str:
    return repr(float(x))


def _v(values) -> str:
    return " ".join(_f(x) for x in values)


def _b(flag: bool) -> str:
    return "true" if flag else "false"


def _scene_element(scene: Scene) -> etree._Element:
    root = etree.Element("scene")
    root.set("version", str(scene.version))
    if scene.name is not None:
        root.set("name", scene.name)
    root.set("gravity", _v(scene.gravity))

    s = scene.simulation
    sim = etree.SubElement(root, "simulation")
    sim.set("dt", _f(s.dt))
    sim.set("duration", _f(s.duration))
    sim.set("friction", _f(s.friction))
    sim.set("restitution", _f(s.restitution))
    for key, value in s.extra.items():
        sim.set(key, str(value))

    for obj in scene.objects:
        root.append(_object_element(obj))
    if scene.inference is not None:
        root.append(_inference_element(scene.inference))
    return root


def _object_element(obj: SceneObject) -> etree._Element:
    el = etree.Element("object")
    el.set("id", obj.id)
    if obj.shape is not None:
        el.set("shape", obj.shape)
    if obj.size is not None:
        el.set("size", _v(obj.size))
    if obj.radius is not None:
        el.set("radius", _f(obj.radius))
    if obj.height is not None:
        el.set("height", _f(obj.height))
    if obj.mesh is not None:
        el.set("mesh", obj.mesh)
    if obj.spheres is not None:
        el.set("spheres", obj.spheres)
    if obj.urdf is not None:
        el.set("urdf", obj.urdf)
    if obj.mjcf is not None:
        el.set("mjcf", obj.mjcf)
    if obj.joints is not None:
        el.set("joints", _v(obj.joints))
    if obj.fixed:
        el.set("fixed", "true")
    for name in ("mass", "density", "friction", "restitution"):
        value = getattr(obj, name)
        if value is not None:
            el.set(name, _f(value))
    pose = etree.SubElement(el, "pose")
    pose.set("position", _v(obj.pose.position))
    pose.set("orientation", _v(obj.pose.orientation))
    if obj.velocity != Velocity():
        vel = etree.SubElement(el, "velocity")
        vel.set("linear", _v(obj.velocity.linear))
        vel.set("angular", _v(obj.velocity.angular))
    for key in obj.keyframes:
        joints = etree.SubElement(el, "joints")
        joints.set("time", _f(key.time))
        joints.set("values", _v(key.values))
    return el


_WRITE = {"vector": lambda v: _v(v), "quat": lambda v: _v(v), "float": lambda v: _f(v),
          "int": lambda v: str(int(v)), "bool": lambda v: _b(v), "cells": lambda v: " ".join(str(int(c)) for c in v),
          "ids": lambda v: " ".join(v)}
"""How each kind of ``INFERENCE_ELEMENTS`` attribute is written."""


def _inference_element(inf: InferenceSettings) -> etree._Element:
    el = etree.Element("inference")
    el.set("source", inf.source)
    if inf.iterations != _default(InferenceSettings, "iterations"):
        el.set("iterations", str(int(inf.iterations)))
    if inf.optimizer != _default(InferenceSettings, "optimizer"):
        el.set("optimizer", inf.optimizer)
    if inf.gradient is not None:
        el.set("gradient", inf.gradient)
    el.set("loss", inf.loss)
    el.set("evaluate", inf.evaluate)
    el.set("seed", str(int(inf.seed)))

    for spec in INFERENCE_ELEMENTS:  # one table for the reader, the writer and the validator
        value = getattr(inf, spec.field)
        items = value if spec.repeated else (() if value is None or (spec.cls is Optimize and value == Optimize())
                                             else (value,))
        for item in items:
            child = etree.SubElement(el, spec.tag)
            for a in spec.attributes:
                v = getattr(item, a.field)
                if v is not None:
                    child.set(a.xml, _WRITE[a.kind](v))
    return el
