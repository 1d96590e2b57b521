"""Hardened parsing of untrusted XML: scene files (``dejaview.scene``) and robot files
(``dejaview.geometry.robot``).

1. bytes: a size limit (default 1 MiB) and an outright refusal of any ``<!DOCTYPE``/``<!ENTITY``
   declaration, before the parser sees the text, so entity bombs and external entities or DTDs
   are never expanded or fetched;
2. well-formedness, with a parser that resolves no entities, loads no DTD, touches no network and
   keeps libxml2's size limits (no XInclude is run).

Errors are :class:`~dejaview.errors.SceneError` naming the file and the line.
"""

from __future__ import annotations

import re

from lxml import etree

from dejaview.errors import SceneError

DEFAULT_MAX_BYTES = 1 << 20
"""Largest document accepted by default (1 MiB): a scene's limit."""

_DTD_RE = re.compile(rb"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)

__all__ = ["DEFAULT_MAX_BYTES", "hardened_parser", "parse_xml"]


def hardened_parser() -> etree.XMLParser:
    """An lxml parser that resolves no entities, loads no DTD and touches no network.

    A fresh one per document: parsers keep an error log and are not thread-safe.
    """
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
    """Parse untrusted XML (``what`` names the kind of file in errors) safely and return its root
    element (no schema check).

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
        root = etree.fromstring(data, hardened_parser())
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
