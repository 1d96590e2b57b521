"""Hardened reading of scene XML (format version 1); the writer is
:mod:`dejaview.scene.writer` (``scene_to_xml``, also exported here).

Reading runs in four stages (1-3 in :mod:`dejaview.scene.parsing`), each raising :class:`~dejaview.errors.SceneError`
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

import math
import os
import re
from pathlib import Path

from dejaview.errors import SceneError
from dejaview.scene.parsing import DEFAULT_MAX_BYTES, SCENE_VERSION, _XML_SPACE, check_structure, load_schema
from dejaview.scene.inference_elements import INFERENCE_ELEMENTS
from dejaview.scene.model import (
    DEFAULT_GRAVITY,
    InferenceSettings,
    JointKeyframe,
    Optimize,
    Pose,
    Scene,
    SceneObject,
    SimulationSettings,
    StartArea,
    Velocity,
)
from dejaview.scene.writer import _default, scene_to_xml
from dejaview.untrusted_xml import _too_large, parse_xml

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

# Counts that XML Schema 1.0 cannot express together with free element order.
_AT_MOST_ONCE = {
    "scene": ("simulation", "inference"),
    "object": ("pose", "velocity"),
    "inference": tuple(e.tag for e in INFERENCE_ELEMENTS if not e.repeated),
}
_REQUIRED_CHILDREN = {"inference": ("target",), "object": ("pose",)}

_SIMULATION_ATTRS = ("dt", "duration", "friction", "restitution")

_FLOAT_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\Z")
_INT_RE = re.compile(r"[+-]?\d+\Z")
_NONFINITE_RE = re.compile(r"[+-]?(?:nan|inf|infinity)\Z", re.IGNORECASE)
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
                      check_files: bool = True, max_steps: int | None = None,
                      root: str | Path | None = None) -> Scene:
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
        root: the folder robots' ``package://`` URIs must resolve inside (``Scene.root``).
    Returns:
        The :class:`Scene` (``path`` unset, ``base_dir`` and ``root`` as given).
    Raises:
        SceneError: naming file, line and element of the first problem.
    """
    from dejaview.scene.validate import validate_scene

    element = parse_xml(text, filename=filename, max_bytes=max_bytes)
    check_structure(element, filename=filename)
    lines: dict[tuple, int | None] = {}
    scene = _SceneReader(filename, lines).read_scene(element)
    base = Path(base_dir) if base_dir is not None else None
    scene = scene.replace(base_dir=base, root=Path(root) if root is not None else None)
    validate_scene(scene, check_files=check_files, lines=lines, file=filename, max_steps=max_steps)
    return scene


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
        keyframes = []
        for j, key_el in enumerate(groups.get("joints", ())):
            self.lines[("object", index, "joints", j)] = key_el.sourceline
            keyframes.append(JointKeyframe(time=self.float_attr(key_el, "time"),
                                           values=self.floats_attr(key_el, "values"), line=key_el.sourceline))
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
            keyframes=tuple(keyframes),
            line=el.sourceline,
        )

    def read_inference(self, el) -> InferenceSettings:
        self.lines[("inference",)] = el.sourceline
        groups = self.grouped(el)
        children = {}
        for spec in INFERENCE_ELEMENTS:  # one table for the reader, the writer and the validator
            found = [self.read_element(spec, child, j if spec.repeated else None)
                     for j, child in enumerate(groups.get(spec.tag, ()))]
            if spec.repeated:
                children[spec.field] = tuple(found)
            else:
                children[spec.field] = found[0] if found else (spec.cls() if spec.cls is Optimize else None)
        return InferenceSettings(
            source=el.get("source"),
            iterations=self.int_attr(el, "iterations", _default(InferenceSettings, "iterations")),
            seed=self.int_attr(el, "seed", _default(InferenceSettings, "seed")),
            optimizer=el.get("optimizer", _default(InferenceSettings, "optimizer")),
            gradient=el.get("gradient", _default(InferenceSettings, "gradient")),
            loss=el.get("loss", _default(InferenceSettings, "loss")),
            evaluate=el.get("evaluate", _default(InferenceSettings, "evaluate")),
            **children,
        )

    def read_element(self, spec, el, index: int | None):
        """One child of ``<inference>`` by its row of ``INFERENCE_ELEMENTS`` (``index``: which of a
        repeated element, for its line's key)."""
        self.lines[(spec.tag,) if index is None else (spec.tag, index)] = el.sourceline
        values = {}
        for a in spec.attributes:
            default = spec.default(a)
            if a.kind == "vector":
                values[a.field] = self.vector_attr(el, a.xml, 3, default)
            elif a.kind == "quat":
                values[a.field] = self.quat_attr(el, a.xml, default)
            elif a.kind == "float":
                values[a.field] = self.float_attr(el, a.xml, default)
            elif a.kind == "int":
                values[a.field] = self.int_attr(el, a.xml, default)
            elif a.kind == "bool":
                values[a.field] = self.bool_attr(el, a.xml, default)
            elif a.kind == "cells":
                values[a.field] = self.ints_attr(el, a.xml, 2, default)
            else:  # "ids": two object ids
                ids = (el.get(a.xml) or "").split()
                if len(ids) != 2:
                    raise self.error(el, f"attribute '{a.xml}' needs two object ids, got {len(ids)}")
                values[a.field] = (ids[0], ids[1])
        if spec.cls is StartArea:
            values["line"] = el.sourceline
        return spec.cls(**values)
