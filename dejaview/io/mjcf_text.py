"""How numbers and names are written into MJCF text (``dejaview.io.mjcf`` and ``mjcf_motion``)."""

from __future__ import annotations


def _num(x) -> str:
    return f"{float(x):.10g}"


def _vec(values) -> str:
    return " ".join(_num(v) for v in values)


def _xml(text) -> str:
    return (str(text).replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;")
            .replace(">", "&gt;"))
