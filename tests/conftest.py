"""Test-wide settings."""

import torch

# many small ops: one intra-op thread is faster and deterministic (see dejaview.cli.options)
torch.set_num_threads(1)


def _hypothesis_draws_from_its_own_pool() -> None:
    """Hypothesis (6.131 and later) also draws numbers found as literals in the loaded modules of
    the code under test, so a derandomized test's examples depended on which test files a
    pytest-xdist worker had imported before it (removing a literal 1e-24 from dejaview.sim
    changed the worlds test_native_schema draws). Its own pool alone keeps the draws the same
    whatever was imported. Hypothesis without that pool: nothing to do."""
    try:
        from hypothesis.internal.conjecture import providers
    except ImportError:
        return
    if hasattr(providers, "_get_local_constants") and hasattr(providers, "_local_constants"):
        empty = providers._local_constants  # never filled: the lookup that fills it is replaced
        providers._get_local_constants = lambda: empty


_hypothesis_draws_from_its_own_pool()


import builtins  # noqa: E402
import errno  # noqa: E402
import io  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture
def disk_full_at(monkeypatch):
    """``disk_full_at(name)``: from then on, in this process, opening a file called ``name`` inside a
    result set being written (a ``.partial-`` folder, ``dejaview.result_set``) fails as on a
    full disk (ENOSPC); ``disk_full_at(None)`` frees the disk. The files written before it stay
    in the folder, as a real full disk leaves them."""
    real_open = builtins.open
    state = {"name": None}

    def open_(file, mode="r", *args, **kwargs):
        path = Path(file) if isinstance(file, (str, Path)) else None
        if (path is not None and state["name"] == path.name and ".partial-" in path.parent.name
                and any(c in mode for c in "wax")):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", open_)
    monkeypatch.setattr(io, "open", open_)  # what pathlib's Path.open calls

    def set_full(name):
        state["name"] = name

    return set_full


def needs_mount_namespace():
    """A skip mark for tests that mount a small tmpfs of their own (a real full disk): where this
    process may not make a mount namespace (``unshare -rm`` fails, e.g. a container without user
    namespaces), the same paths are tested with a patched writer instead (``disk_full_at``). One
    check for the tests and ``dejaview bench soak`` (``bench/soak.py``'s ``can_mount``)."""
    from dejaview.cli.bench import bench_module

    return pytest.mark.skipif(not bench_module("soak").can_mount(),
                              reason="needs a mount namespace (unshare -rm) for a small tmpfs")
