"""Writing scene XML (format version 1): ``scene_to_xml``, the inverse of
:mod:`dejaview.scene.xml`'s reader (a written scene reads back equal)."""

from __future__ import annotations

from lxml import etree

from dejaview.errors import SceneError
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
    return el


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

    for t in inf.targets:
        target = etree.SubElement(el, "target")
        target.set("position", _v(t.position))
        if t.orientation is not None:
            target.set("orientation", _v(t.orientation))
        if t.linear_velocity is not None:
            target.set("linear-velocity", _v(t.linear_velocity))
        if t.angular_velocity is not None:
            target.set("angular-velocity", _v(t.angular_velocity))
        if t.time is not None:
            target.set("time", _f(t.time))
        if t.moving is not None:
            target.set("moving", _b(t.moving))

    if inf.optimize != Optimize():
        o = etree.SubElement(el, "optimize")
        o.set("position", _b(inf.optimize.position))
        o.set("orientation", _b(inf.optimize.orientation))
        o.set("linear-velocity", _b(inf.optimize.linear_velocity))
        o.set("angular-velocity", _b(inf.optimize.angular_velocity))
    if inf.start_area is not None:
        s = etree.SubElement(el, "start-area")
        s.set("min", _v(inf.start_area.min))
        s.set("max", _v(inf.start_area.max))
    if inf.exploration is not None:
        x = etree.SubElement(el, "exploration")
        x.set("epsilon", _f(inf.exploration.epsilon))
        x.set("patience", str(int(inf.exploration.patience)))
    for pen in inf.penalties:
        p = etree.SubElement(el, "penalty")
        p.set("between", " ".join(pen.between))
        p.set("weight", _f(pen.weight))
    if inf.heatmap is not None:
        h = etree.SubElement(el, "heatmap")
        h.set("cells", " ".join(str(int(c)) for c in inf.heatmap.cells))
        h.set("samples", str(int(inf.heatmap.samples)))
        h.set("sigma", _f(inf.heatmap.sigma))
    for tag, value, attrs in (("prior", inf.prior, (("speed", "speed"), ("spin", "spin"), ("tilt", "tilt"))),
                              ("observation", inf.observation,
                               (("sigma", "sigma"), ("angle-sigma", "angle_sigma"), ("rest-speed", "rest_speed"),
                                ("rest-spin", "rest_spin"))),
                              ("model-uncertainty", inf.model_uncertainty,
                               (("friction", "friction"), ("restitution", "restitution")))):
        if value is not None:
            e = etree.SubElement(el, tag)
            for attr, name in attrs:
                if getattr(value, name) is not None:
                    e.set(attr, _f(getattr(value, name)))
    if inf.posterior is not None:
        etree.SubElement(el, "posterior").set("samples", str(int(inf.posterior.samples)))
    return el
