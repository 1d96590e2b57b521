"""Hardened reading and writing of scene XML (format version 1).

Reading runs in four stages, each raising :class:`~dejaview.errors.SceneError`
naming the file, the line and the element of the first problem:

1. bytes: a size limit (default 1 MiB) and an outright refusal of any
   ``<!DOCTYPE``/``<!ENTITY`` declaration, before the parser sees the text, so
   entity bombs and external entities or DTDs are never expanded or fetched;
2. well-formedness, with a parser that resolves no entities, loads no DTD,
   touches no network and keeps libxml2's size limits (no XInclude is run);
3. structure, against the XML Schema ``scene.xsd`` shipped in this package
   (which elements go where, which attributes each takes);
4. values: strict numbers, vectors of the right length, booleans, then the
   semantic checks of :mod:`dejaview.scene.validate`.

Line numbers are libxml2's: the line where an element's start tag ends.
"""

from __future__ import annotations

import difflib
import functools
import math
import os
import re
import threading
from importlib import resources
from pathlib import Path

from lxml import etree

from dejaview.errors import SceneError
from dejaview.scene.model import (
    DEFAULT_GRAVITY,
    Exploration,
    HeatmapSettings,
    InferenceSettings,
    ModelUncertainty,
    Observation,
    PosteriorSamples,
    Optimize,
    Penalty,
    Pose,
    Prior,
    Scene,
    SceneObject,
    SimulationSettings,
    StartArea,
    Target,
    Velocity,
)

__all__ = [
    "DEFAULT_MAX_BYTES",
    "SCENE_VERSION",
    "normalize_quaternion",
    "parse_xml",
    "check_structure",
    "load_schema",
    "read_scene_file",
    "read_scene_string",
    "scene_to_xml",
]

DEFAULT_MAX_BYTES = 1 << 20
"""Largest scene accepted by default (1 MiB)."""

SCENE_VERSION = "1"
"""The only format version this reader knows."""

# Counts that XML Schema 1.0 cannot express together with free element order.
_AT_MOST_ONCE = {
    "scene": ("simulation", "inference"),
    "inference": ("target", "optimize", "start-area", "exploration", "heatmap", "prior", "observation",
                  "model-uncertainty", "posterior"),
}
_REQUIRED_CHILDREN = {"inference": ("target",)}

_SIMULATION_ATTRS = ("dt", "duration", "friction", "restitution")

# Matches a declaration that could define entities or pull in a DTD.
_DTD_RE = re.compile(rb"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)
_FLOAT_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\Z")
_INT_RE = re.compile(r"[+-]?\d+\Z")
_NONFINITE_RE = re.compile(r"[+-]?(?:nan|inf|infinity)\Z", re.IGNORECASE)
_XML_SPACE = " \t\r\n"
_BOOLEANS = {"true": True, "1": True, "false": False, "0": False}
# Quaternions whose squared norm is this close to 1 are kept as written, so
# normalising is idempotent and a written scene reads back bit for bit.
_UNIT_TOLERANCE = 1e-12


# ---------------------------------------------------------------------------
# public entry points
# ---------------------------------------------------------------------------
def read_scene_file(path: str | Path, max_bytes: int = DEFAULT_MAX_BYTES,
                    check_files: bool = True, max_steps: int | None = None) -> Scene:
    """Read, check and return the scene in the XML file ``path``.

    Args:
        path: the scene file. Relative ``mesh``/``spheres`` names resolve
            against its folder.
        max_bytes: refuse files larger than this.
        check_files: check that mesh and sphere files exist.
        max_steps: step budget of a simulation of the scene (default
            ``dejaview.scene.bounds.max_steps()``).
    Returns:
        The :class:`Scene`, with ``path`` and ``base_dir`` set.
    Raises:
        SceneError: naming file, line and element of the first problem.
    """
    path = Path(path)
    filename = str(path)
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > max_bytes:
                raise SceneError(_too_large(size, max_bytes), filename)
            # Read one byte past the limit: st_size is 0 for pipes and /dev files.
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise SceneError(f"cannot read scene file: {exc.strerror or exc}", filename) from None
    scene = read_scene_string(data, base_dir=path.absolute().parent, filename=filename,
                              max_bytes=max_bytes, check_files=check_files, max_steps=max_steps)
    return scene.replace(path=path)


def read_scene_string(text: str | bytes, base_dir: str | Path | None = None,
                      filename: str = "<string>", max_bytes: int = DEFAULT_MAX_BYTES,
                      check_files: bool = True, max_steps: int | None = None) -> Scene:
    """Parse, check and return scene XML given as text or bytes.

    Args:
        text: the XML. ``str`` is encoded as UTF-8; bytes must be UTF-8.
        base_dir: folder that relative ``mesh``/``spheres`` names resolve
            against (None: the current directory).
        filename: name used in error messages.
        max_bytes: refuse documents larger than this many bytes.
        check_files: check that mesh and sphere files exist.
        max_steps: step budget of a simulation of the scene (default
            ``dejaview.scene.bounds.max_steps()``).
    Returns:
        The :class:`Scene` (``path`` unset, ``base_dir`` as given).
    Raises:
        SceneError: naming file, line and element of the first problem.
    """
    from dejaview.scene.validate import validate_scene

    root = parse_xml(text, filename=filename, max_bytes=max_bytes)
    check_structure(root, filename=filename)
    lines: dict[tuple, int | None] = {}
    scene = _SceneReader(filename, lines).read_scene(root)
    base = Path(base_dir) if base_dir is not None else None
    scene = scene.replace(base_dir=base)
    validate_scene(scene, check_files=check_files, lines=lines, file=filename, max_steps=max_steps)
    return scene


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


def normalize_quaternion(q, name: str = "orientation") -> tuple[float, float, float, float]:
    """Return ``q`` (w x y z) scaled to unit length.

    Quaternions already of unit length (to within rounding) are returned
    unchanged, so that normalising twice gives the same floats.

    Raises:
        ValueError: for a zero (or non-finite) quaternion.
    """
    w, x, y, z = (float(c) for c in q)
    n2 = w * w + x * x + y * y + z * z
    if not math.isfinite(n2):
        raise ValueError(f"{name} is not finite")
    if n2 == 0.0:
        raise ValueError(f"{name} is a zero quaternion")
    if abs(n2 - 1.0) <= _UNIT_TOLERANCE:
        return (w, x, y, z)
    n = math.sqrt(n2)
    return (w / n, x / n, y / n, z / n)


# ---------------------------------------------------------------------------
# stage 1-2: bytes and well-formedness
# ---------------------------------------------------------------------------
def _make_parser() -> etree.XMLParser:
    # A fresh parser per document: parsers keep an error log and are not thread-safe.
    return etree.XMLParser(
        resolve_entities=False,
        no_network=True,
        load_dtd=False,
        dtd_validation=False,
        huge_tree=False,
        remove_comments=True,
        remove_pis=True,
        collect_ids=False,
        encoding="utf-8",
    )


def parse_xml(text: str | bytes, filename: str = "<string>",
              max_bytes: int = DEFAULT_MAX_BYTES, what: str = "scene files") -> etree._Element:
    """Parse scene XML (or other untrusted XML: ``what`` names it in errors) safely and return
    its root element (no schema check).

    Refuses documents over ``max_bytes``, empty documents, any DOCTYPE or
    ENTITY declaration (never expanded, never fetched) and malformed XML.

    Raises:
        SceneError: naming the file and line.
    """
    data = text.encode("utf-8") if isinstance(text, str) else bytes(text)
    if len(data) > max_bytes:
        raise SceneError(_too_large(len(data), max_bytes), filename)
    if not data.strip(b" \t\r\n\xef\xbb\xbf"):
        raise SceneError("empty file: no XML at all", filename, 1)
    match = _DTD_RE.search(data)
    if match:
        kind = match.group(1).decode("ascii").upper()
        line = data.count(b"\n", 0, match.start()) + 1
        raise SceneError(
            f"{kind} declarations are not allowed in {what} "
            "(entities and DTDs are refused, never expanded or fetched)",
            filename, line, "!" + kind)
    try:
        root = etree.fromstring(data, _make_parser())
    except etree.XMLSyntaxError as exc:
        message = re.sub(r", line \d+, column \d+$", "", " ".join((exc.msg or "syntax error").split()))
        raise SceneError(f"not well-formed XML: {message}", filename,
                         exc.lineno or 1) from None
    # Defence in depth: the byte scan above should make this unreachable.
    docinfo = root.getroottree().docinfo
    if docinfo.doctype or docinfo.internalDTD is not None or docinfo.externalDTD is not None:
        raise SceneError(f"DOCTYPE declarations are not allowed in {what}",
                         filename, 1, "!DOCTYPE")
    return root


def _too_large(size: int, max_bytes: int) -> str:
    return f"scene is too large: {size} bytes, over the {_human_bytes(max_bytes)} limit"


def _human_bytes(n: int) -> str:
    if n >= 1 << 20 and n % (1 << 20) == 0:
        return f"{n >> 20} MiB"
    if n >= 1 << 10 and n % (1 << 10) == 0:
        return f"{n >> 10} KiB"
    return f"{n} bytes"


# ---------------------------------------------------------------------------
# stage 3: structure (XML Schema)
# ---------------------------------------------------------------------------
_XS = "{http://www.w3.org/2001/XMLSchema}"
_schema_lock = threading.Lock()


@functools.lru_cache(maxsize=1)
def _schema_bytes() -> bytes:
    return resources.files("dejaview.scene").joinpath("scene.xsd").read_bytes()


@functools.lru_cache(maxsize=1)
def load_schema() -> etree.XMLSchema:
    """The XML Schema of scene files (``scene.xsd`` in this package), cached."""
    doc = etree.fromstring(_schema_bytes(), _make_parser())
    return etree.XMLSchema(doc)


@functools.lru_cache(maxsize=1)
def _schema_outline() -> dict[str, dict[str, tuple[str, ...]]]:
    """Per element name: its declared attributes, children and required children.

    Read from ``scene.xsd`` itself so error hints never disagree with it.
    """
    doc = etree.fromstring(_schema_bytes(), _make_parser())
    types = {t.get("name"): t for t in doc.iter(_XS + "complexType")}
    outline = {}
    for decl in doc.iter(_XS + "element"):
        ctype = types.get(decl.get("type"))
        if ctype is None:
            continue
        children = [e for e in ctype.iter(_XS + "element")]
        required = [e.get("name") for e in children
                    if e.get("minOccurs", "1") != "0"
                    and e.getparent().tag in (_XS + "all", _XS + "sequence")]
        outline[decl.get("name")] = {
            "attributes": tuple(a.get("name") for a in ctype.iter(_XS + "attribute")),
            "children": tuple(e.get("name") for e in children),
            "required_children": tuple(required),
        }
    return outline


def check_structure(root: etree._Element, filename: str = "<string>") -> None:
    """Check the root element, the version and the schema.

    Raises:
        SceneError: for a wrong root, a missing or unknown version, or the
            first schema violation, with a one-line readable reason.
    """
    if root.tag != "scene":
        tag = _display_tag(root)
        raise SceneError(f"root element is <{tag}>, expected <scene>", filename, root.sourceline, tag)
    version = root.get("version")
    if version is None:
        raise SceneError("missing required attribute 'version' (this reader knows "
                         f"version {SCENE_VERSION})", filename, root.sourceline, "scene")
    if version.strip(_XML_SPACE) != SCENE_VERSION:
        raise SceneError(f"unknown scene version {version!r} (this reader knows version "
                         f"{SCENE_VERSION})", filename, root.sourceline, "scene")
    schema = load_schema()
    with _schema_lock:
        valid = schema.validate(root)
        errors = list(schema.error_log)
    if not valid:
        first = errors[0] if errors else None
        if first is None:
            raise SceneError("does not match the scene schema", filename, root.sourceline, "scene")
        element, reason = _explain_schema_error(first.message, first.path)
        if element and element.startswith("{"):
            # libxml2 writes {uri}name; show the prefix the author wrote instead.
            found = next(root.iter(element), None)
            if found is not None:
                shown = _display_tag(found)
                reason = reason.replace(element, shown)
                element = shown
        raise SceneError(reason, filename, first.line or None, element)


def _display_tag(el) -> str:
    """The tag as written in the file: ``prefix:name`` rather than ``{uri}name``."""
    qname = etree.QName(el)
    if el.prefix:
        return f"{el.prefix}:{qname.localname}"
    if qname.namespace:  # a default namespace: keep it visible, it is the problem
        return f"{{{qname.namespace}}}{qname.localname}"
    return qname.localname


_SCHEMA_MSG_RE = re.compile(r"Element '(?P<el>[^']*)'(?:, attribute '(?P<attr>[^']*)')?: (?P<rest>.*)",
                            re.DOTALL)


def _explain_schema_error(message: str, path: str | None) -> tuple[str | None, str]:
    """Turn a libxml2 schema message into (element, readable one-line reason)."""
    message = " ".join(message.split())
    m = _SCHEMA_MSG_RE.match(message)
    if not m:
        return None, message.rstrip(".")
    element, attr, rest = m.group("el"), m.group("attr"), m.group("rest").strip()
    outline = _schema_outline()
    parent = _parent_from_path(path)
    if attr is not None and "is not allowed" in rest:
        known = outline.get(element, {}).get("attributes", ())
        return element, f"unknown attribute '{attr}'{_did_you_mean(attr, known)}"
    req = re.match(r"The attribute '([^']*)' is required but missing", rest)
    if req:
        return element, f"missing required attribute '{req.group(1)}'"
    if rest.startswith("This element is not expected"):
        allowed = outline.get(parent, {}).get("children", ()) if parent else ()
        if element in allowed:
            return element, f"<{element}> may appear only once inside <{parent}>"
        where = f" inside <{parent}>" if parent else ""
        hint = _did_you_mean(element, allowed)
        if not hint and allowed:
            hint = " (allowed: " + ", ".join(allowed) + ")"
        return element, f"unknown element <{element}>{where}{hint}"
    if rest.startswith("Missing child element"):
        required = outline.get(element, {}).get("required_children", ())
        if required:
            names = ", ".join(f"<{r}>" for r in required)
            return element, f"missing required child element {names}"
        return element, "missing child element"
    if rest.startswith("Character content"):
        return element, f"text is not allowed inside <{element}>"
    reason = rest.rstrip(".")
    if attr is not None:
        reason = f"attribute '{attr}': {reason}"
    return element, reason


def _parent_from_path(path: str | None) -> str | None:
    if not path:
        return None
    parts = [re.sub(r"\[\d+\]$", "", p) for p in path.split("/") if p]
    return parts[-2] if len(parts) >= 2 else None


def _did_you_mean(name: str, candidates) -> str:
    close = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


# ---------------------------------------------------------------------------
# stage 4: values -> dataclasses
# ---------------------------------------------------------------------------
class _SceneReader:
    """Builds the dataclasses from a schema-valid tree, parsing values strictly.

    ``lines`` is filled with the line of every element, keyed as
    :mod:`dejaview.scene.validate` expects, so semantic errors can name it.
    """

    def __init__(self, filename: str, lines: dict[tuple, int | None]):
        self.filename = filename
        self.lines = lines

    # -- helpers -------------------------------------------------------------
    def error(self, el, reason: str) -> SceneError:
        return SceneError(reason, self.filename, el.sourceline, el.tag)

    @staticmethod
    def children(el) -> list:
        return [c for c in el if isinstance(c.tag, str)]

    def grouped(self, el) -> dict[str, list]:
        groups: dict[str, list] = {}
        for child in self.children(el):
            groups.setdefault(child.tag, []).append(child)
        for tag in _AT_MOST_ONCE.get(el.tag, ()):
            if len(groups.get(tag, ())) > 1:
                raise self.error(groups[tag][1], f"<{tag}> may appear only once inside <{el.tag}>")
        for tag in _REQUIRED_CHILDREN.get(el.tag, ()):
            if tag not in groups:
                raise self.error(el, f"missing required child element <{tag}>")
        return groups

    def number(self, el, name: str, token: str, what: str = "a number") -> float:
        if _FLOAT_RE.match(token):
            value = float(token)
            if math.isfinite(value):
                return value
            raise self.error(el, f"attribute '{name}' is not finite ({token!r} overflows)")
        if _NONFINITE_RE.match(token):
            raise self.error(el, f"attribute '{name}' is not finite ({token!r}); "
                                 "NaN and infinity are refused")
        raise self.error(el, f"attribute '{name}': {token!r} is not {what}")

    def float_attr(self, el, name: str, default=None):
        raw = el.get(name)
        if raw is None:
            return default
        tokens = raw.split()
        if len(tokens) != 1:
            raise self.error(el, f"attribute '{name}' needs 1 number, got {len(tokens)}")
        return self.number(el, name, tokens[0])

    def vector_attr(self, el, name: str, n: int, default=None):
        raw = el.get(name)
        if raw is None:
            return default
        tokens = raw.split()
        if len(tokens) != n:
            raise self.error(el, f"attribute '{name}' needs {n} numbers, got {len(tokens)}")
        return tuple(self.number(el, name, t) for t in tokens)

    def floats_attr(self, el, name: str, default=None):
        """Any number (zero included) of whitespace-separated numbers, as a tuple."""
        raw = el.get(name)
        if raw is None:
            return default
        return tuple(self.number(el, name, t) for t in raw.split())

    def quat_attr(self, el, name: str, default=None):
        q = self.vector_attr(el, name, 4)
        if q is None:
            return default
        try:
            return normalize_quaternion(q, f"attribute '{name}'")
        except ValueError as exc:
            raise self.error(el, f"{exc} (w x y z must not all be 0)") from None

    def integer(self, el, name: str, token: str) -> int:
        if not _INT_RE.match(token):
            raise self.error(el, f"attribute '{name}': {token!r} is not an integer")
        try:
            return int(token)
        except ValueError:  # beyond int()'s digit limit
            raise self.error(el, f"attribute '{name}': integer is too large") from None

    def int_attr(self, el, name: str, default=None):
        raw = el.get(name)
        if raw is None:
            return default
        tokens = raw.split()
        if len(tokens) != 1:
            raise self.error(el, f"attribute '{name}' needs 1 integer, got {len(tokens)}")
        return self.integer(el, name, tokens[0])

    def ints_attr(self, el, name: str, n: int, default=None):
        raw = el.get(name)
        if raw is None:
            return default
        tokens = raw.split()
        if len(tokens) != n:
            raise self.error(el, f"attribute '{name}' needs {n} integers, got {len(tokens)}")
        return tuple(self.integer(el, name, t) for t in tokens)

    def bool_attr(self, el, name: str, default: bool) -> bool:
        raw = el.get(name)
        if raw is None:
            return default
        value = _BOOLEANS.get(raw.strip(_XML_SPACE))
        if value is None:
            raise self.error(el, f"attribute '{name}': {raw!r} is not a boolean "
                                 "(use true, false, 1 or 0)")
        return value

    # -- elements ------------------------------------------------------------
    def read_scene(self, el) -> Scene:
        self.lines[("scene",)] = el.sourceline
        groups = self.grouped(el)
        simulation = SimulationSettings()
        if "simulation" in groups:
            simulation = self.read_simulation(groups["simulation"][0])
        objects = tuple(self.read_object(o, i) for i, o in enumerate(groups.get("object", ())))
        inference = None
        if "inference" in groups:
            inference = self.read_inference(groups["inference"][0])
        return Scene(
            objects=objects,
            version=int(SCENE_VERSION),
            name=el.get("name"),
            gravity=self.vector_attr(el, "gravity", 3, DEFAULT_GRAVITY),
            simulation=simulation,
            inference=inference,
        )

    def read_simulation(self, el) -> SimulationSettings:
        self.lines[("simulation",)] = el.sourceline
        d = SimulationSettings()
        extra = {k: v for k, v in el.attrib.items() if k not in _SIMULATION_ATTRS}
        return SimulationSettings(
            dt=self.float_attr(el, "dt", d.dt),
            duration=self.float_attr(el, "duration", d.duration),
            friction=self.float_attr(el, "friction", d.friction),
            restitution=self.float_attr(el, "restitution", d.restitution),
            extra=extra,
        )

    def read_object(self, el, index: int) -> SceneObject:
        self.lines[("object", index)] = el.sourceline
        groups = self.grouped(el)
        pose_el = groups["pose"][0]
        self.lines[("object", index, "pose")] = pose_el.sourceline
        pose = Pose(position=self.vector_attr(pose_el, "position", 3),
                    orientation=self.quat_attr(pose_el, "orientation", Pose().orientation))
        velocity = Velocity()
        if "velocity" in groups:
            vel_el = groups["velocity"][0]
            self.lines[("object", index, "velocity")] = vel_el.sourceline
            velocity = Velocity(linear=self.vector_attr(vel_el, "linear", 3, velocity.linear),
                                angular=self.vector_attr(vel_el, "angular", 3, velocity.angular))
        return SceneObject(
            id=el.get("id"),
            pose=pose,
            velocity=velocity,
            shape=el.get("shape"),
            size=self.vector_attr(el, "size", 3),
            radius=self.float_attr(el, "radius"),
            height=self.float_attr(el, "height"),
            mesh=el.get("mesh"),
            spheres=el.get("spheres"),
            fixed=self.bool_attr(el, "fixed", False),
            mass=self.float_attr(el, "mass"),
            density=self.float_attr(el, "density"),
            friction=self.float_attr(el, "friction"),
            restitution=self.float_attr(el, "restitution"),
            urdf=el.get("urdf"),
            mjcf=el.get("mjcf"),
            joints=self.floats_attr(el, "joints"),
            line=el.sourceline,
        )

    def read_inference(self, el) -> InferenceSettings:
        self.lines[("inference",)] = el.sourceline
        groups = self.grouped(el)

        t = groups["target"][0]
        self.lines[("target",)] = t.sourceline
        target = Target(
            position=self.vector_attr(t, "position", 3),
            orientation=self.quat_attr(t, "orientation", _default(Target, "orientation")),
            linear_velocity=self.vector_attr(t, "linear-velocity", 3),
            angular_velocity=self.vector_attr(t, "angular-velocity", 3),
            time=self.float_attr(t, "time"),
        )
        optimize = Optimize()
        if "optimize" in groups:
            o = groups["optimize"][0]
            self.lines[("optimize",)] = o.sourceline
            optimize = Optimize(
                position=self.bool_attr(o, "position", True),
                orientation=self.bool_attr(o, "orientation", True),
                linear_velocity=self.bool_attr(o, "linear-velocity", True),
                angular_velocity=self.bool_attr(o, "angular-velocity", True),
            )
        start_area = None
        if "start-area" in groups:
            s = groups["start-area"][0]
            self.lines[("start-area",)] = s.sourceline
            start_area = StartArea(min=self.vector_attr(s, "min", 3), max=self.vector_attr(s, "max", 3))
        exploration = None
        if "exploration" in groups:
            x = groups["exploration"][0]
            self.lines[("exploration",)] = x.sourceline
            de = Exploration()
            exploration = Exploration(epsilon=self.float_attr(x, "epsilon", de.epsilon),
                                      patience=self.int_attr(x, "patience", de.patience))
        penalties = []
        for j, p in enumerate(groups.get("penalty", ())):
            self.lines[("penalty", j)] = p.sourceline
            between = p.get("between").split()
            if len(between) != 2:
                raise self.error(p, f"attribute 'between' needs two object ids, got {len(between)}")
            penalties.append(Penalty(between=(between[0], between[1]),
                                     weight=self.float_attr(p, "weight", _default(Penalty, "weight"))))
        heatmap = None
        if "heatmap" in groups:
            h = groups["heatmap"][0]
            self.lines[("heatmap",)] = h.sourceline
            dh = HeatmapSettings()
            heatmap = HeatmapSettings(cells=self.ints_attr(h, "cells", 2, dh.cells),
                                      samples=self.int_attr(h, "samples", dh.samples),
                                      sigma=self.float_attr(h, "sigma", dh.sigma))
        prior = None
        if "prior" in groups:
            pr = groups["prior"][0]
            self.lines[("prior",)] = pr.sourceline
            prior = Prior(speed=self.float_attr(pr, "speed"), spin=self.float_attr(pr, "spin"),
                          tilt=self.float_attr(pr, "tilt"))
        observation = None
        if "observation" in groups:
            ob = groups["observation"][0]
            self.lines[("observation",)] = ob.sourceline
            observation = Observation(sigma=self.float_attr(ob, "sigma"),
                                      angle_sigma=self.float_attr(ob, "angle-sigma"))
        model_uncertainty = None
        if "model-uncertainty" in groups:
            mu = groups["model-uncertainty"][0]
            self.lines[("model-uncertainty",)] = mu.sourceline
            model_uncertainty = ModelUncertainty(friction=self.float_attr(mu, "friction"),
                                                 restitution=self.float_attr(mu, "restitution"))
        posterior = None
        if "posterior" in groups:
            po = groups["posterior"][0]
            self.lines[("posterior",)] = po.sourceline
            posterior = PosteriorSamples(
                samples=self.int_attr(po, "samples", _default(PosteriorSamples, "samples")))
        return InferenceSettings(
            source=el.get("source"),
            target=target,
            iterations=self.int_attr(el, "iterations", _default(InferenceSettings, "iterations")),
            seed=self.int_attr(el, "seed", _default(InferenceSettings, "seed")),
            optimizer=el.get("optimizer", _default(InferenceSettings, "optimizer")),
            gradient=el.get("gradient", _default(InferenceSettings, "gradient")),
            loss=el.get("loss", _default(InferenceSettings, "loss")),
            evaluate=el.get("evaluate", _default(InferenceSettings, "evaluate")),
            optimize=optimize,
            start_area=start_area,
            exploration=exploration,
            penalties=tuple(penalties),
            heatmap=heatmap,
            prior=prior,
            observation=observation,
            model_uncertainty=model_uncertainty,
            posterior=posterior,
        )


def _default(cls, name: str):
    """The default value of dataclass field ``name`` (the model is the one place for it)."""
    return cls.__dataclass_fields__[name].default


# ---------------------------------------------------------------------------
# writer
# ---------------------------------------------------------------------------
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

    t = inf.target
    target = etree.SubElement(el, "target")
    target.set("position", _v(t.position))
    target.set("orientation", _v(t.orientation))
    if t.linear_velocity is not None:
        target.set("linear-velocity", _v(t.linear_velocity))
    if t.angular_velocity is not None:
        target.set("angular-velocity", _v(t.angular_velocity))
    if t.time is not None:
        target.set("time", _f(t.time))

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
                               (("sigma", "sigma"), ("angle-sigma", "angle_sigma"))),
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
