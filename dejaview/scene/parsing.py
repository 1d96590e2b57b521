"""Hardened parsing of scene XML: stages 1-3 of ``dejaview.scene.xml``'s reader.

1. bytes and 2. well-formedness: ``dejaview.untrusted_xml.parse_xml``, shared with the robot files'
   reader (a size limit, no DOCTYPE or ENTITY declaration, a parser that resolves nothing);
3. structure, against the XML Schema ``scene.xsd`` shipped in this package (which elements go
   where, which attributes each takes), with schema errors explained in one line.

Each stage raises :class:`~dejaview.errors.SceneError` naming the file, the line and the element.
"""

from __future__ import annotations

import difflib
import functools
import re
import threading
from importlib import resources

from lxml import etree

from dejaview.errors import SceneError
from dejaview.untrusted_xml import DEFAULT_MAX_BYTES, hardened_parser

SCENE_VERSION = "1"
"""The only format version this reader knows."""

_XML_SPACE = " \t\r\n"

__all__ = ["DEFAULT_MAX_BYTES", "SCENE_VERSION", "check_structure", "load_schema"]


# ---------------------------------------------------------------------------
# stage 3: structure (XML Schema)
# ---------------------------------------------------------------------------
_XS = "{http://www.w3.org/2001/XMLSchema}"
_schema_lock = threading.Lock()


@functools.lru_cache(maxsize=1)
def _schema_bytes() -> bytes:
    return resources.files("dejaview.scene").joinpath("scene.xsd").read_bytes()


_schema: etree.XMLSchema | None = None


def load_schema() -> etree.XMLSchema:
    """The XML Schema of scene files (``scene.xsd`` in this package), built once per process.

    Built under ``_schema_lock``: libxml2 sets up its table of built-in XML Schema types on the
    first schema it parses, and two threads doing that at once (the server reads scenes in
    worker threads) leave the table broken for the life of the process (every later parse
    fails with "the given type is not a built-in type") or crash it.
    """
    global _schema
    with _schema_lock:
        if _schema is None:
            doc = etree.fromstring(_schema_bytes(), hardened_parser())
            _schema = etree.XMLSchema(doc)
        return _schema


@functools.lru_cache(maxsize=1)
def _schema_outline() -> dict[str, dict[str, tuple[str, ...]]]:
    """Per element name: its declared attributes, children and required children.

    Read from ``scene.xsd`` itself so error hints never disagree with it.
    """
    doc = etree.fromstring(_schema_bytes(), hardened_parser())
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
