"""Hardened parsing of scene XML: stages 1-3 of ``dejaview.scene.xml``'s reader.

1. bytes: a size limit (default 1 MiB) and an outright refusal of any ``<!DOCTYPE``/``<!ENTITY``
   declaration, before the parser sees the text, so entity bombs and external entities or DTDs
   are never expanded or fetched;
2. well-formedness, with a parser that resolves no entities, loads no DTD, touches no network and
   keeps libxml2's size limits (no XInclude is run);
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

DEFAULT_MAX_BYTES = 1 << 20
"""Largest scene accepted by default (1 MiB)."""

SCENE_VERSION = "1"
"""The only format version this reader knows."""

_DTD_RE = re.compile(rb"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)
_XML_SPACE = " \t\r\n"

__all__ = ["DEFAULT_MAX_BYTES", "SCENE_VERSION", "check_structure", "load_schema", "parse_xml"]


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
