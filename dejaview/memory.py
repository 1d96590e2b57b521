"""How much memory a process may use, and the check that refuses a request sized over it.

Every command and job sizes what it was asked before it runs (the posterior sampler:
``dejaview.inference.sizing.sampler_bytes``; a simulation's records:
``dejaview.sim.simulate``) and calls ``check``: what the process holds now plus the request's
estimate must fit the limit, else a ``ResourceError`` names the request, the estimate and the
limit in one line (``dejaview`` exits with status 2; the service's job fails with
``limit_exceeded``). Nothing is allocated first: the error comes before the work.

The limit is ``DEJAVIEW_MEMORY_LIMIT`` (bytes, or with a suffix: ``512M``, ``8G``) where it is
set, else ``MACHINE_SHARE`` of the machine's memory (the smaller of ``MemTotal`` and the
cgroup's ``memory.max``): the rest is left to the system and to other programs. A server
divides its limit between its workers (``dejaview.server.config.ServerConfig.job_memory_bytes``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from dejaview.errors import ResourceError

ENV = "DEJAVIEW_MEMORY_LIMIT"
MACHINE_SHARE = 0.8
"""Share of the machine's memory a process may use when ``DEJAVIEW_MEMORY_LIMIT`` is not set."""

_UNITS = {"": 1, "B": 1, "K": 2 ** 10, "M": 2 ** 20, "G": 2 ** 30, "T": 2 ** 40}


def parse_size(text: str) -> int:
    """Bytes of a size such as ``"123456"``, ``"512M"``, ``"8G"``, ``"1.5GiB"`` (binary units).

    Raises:
        ResourceError: text that is not a positive size.
    """
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMGT]?)(I?B)?\s*", str(text), re.IGNORECASE)
    if m is None or float(m.group(1)) <= 0:
        raise ResourceError(f"{ENV}={text!r}", "is not a size: give bytes, or a number with K, M, G or T "
                                               "(e.g. 8G)")
    return int(float(m.group(1)) * _UNITS[m.group(2).upper()])


def format_size(n: float) -> str:
    """``n`` bytes in words: ``"19.1 GiB"``, ``"512 MiB"``, ``"3.2e+06 TiB"``."""
    for unit, scale in (("TiB", 2 ** 40), ("GiB", 2 ** 30), ("MiB", 2 ** 20), ("KiB", 2 ** 10)):
        if n >= scale:
            v = n / scale
            return f"{v:.3g} {unit}" if v < 1000 else f"{v:,.0f} {unit}"
    return f"{int(n)} bytes"


def machine_bytes() -> int:
    """The memory this process's machine (or its cgroup, where that is smaller) holds, in bytes."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return total


def limit() -> tuple[int, str]:
    """The memory limit in bytes, and where it comes from (for the error line).

    Raises:
        ResourceError: a ``DEJAVIEW_MEMORY_LIMIT`` that is not a size.
    """
    text = os.environ.get(ENV)
    if text:
        return parse_size(text), ENV
    total = machine_bytes()
    return int(MACHINE_SHARE * total), f"{MACHINE_SHARE:.0%} of the machine's {format_size(total)}; set {ENV}"


def resident() -> int:
    """Bytes this process holds now (``VmRSS``; 0 where ``/proc`` is not there)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def check(request: str, need: int, limit_bytes: int | None = None) -> None:
    """Refuse ``request`` (words naming it: ``"8000000 posterior samples"``) when what this process
    holds now plus ``need`` bytes is over the limit (``limit_bytes``, else ``limit()``).

    Raises:
        ResourceError: one line naming the request, the estimate and the limit.
    """
    if limit_bytes is None:
        limit_bytes, source = limit()
    else:
        source = "this server's limit for one job"
    held = resident()
    if held + need > limit_bytes:
        raise ResourceError(request, f"would need about {format_size(held + need)} of memory "
                                     f"({format_size(need)} for the request, {format_size(held)} held "
                                     f"already), over the limit of {format_size(limit_bytes)} ({source})",
                            need=held + need, limit=limit_bytes)
