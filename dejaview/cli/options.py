"""Options shared by the simulate, solve and heatmap commands (scene-format spec, "Command line"), and
``--package-path`` of every command that reads robots."""

from __future__ import annotations

import functools
import os
import sys

import click

from dejaview.scene.model import GRADIENTS, OPTIMIZERS  # a leaf module: --help stays cheap


class RegistryChoice(click.Choice):
    """A ``click.Choice`` whose names are read from where they are registered, on first use: the
    commands' ``--help`` and their arguments import it, ``dejaview --help`` does not (it costs torch)."""

    def __init__(self, module: str, name: str):
        self._where = (module, name)
        self.case_sensitive = True

    @functools.cached_property
    def choices(self) -> tuple[str, ...]:
        import importlib

        module, name = self._where
        return tuple(getattr(importlib.import_module(module), name))


BACKENDS = RegistryChoice("dejaview.backends", "BACKENDS")
ENGINES = RegistryChoice("dejaview.sim.native", "ENGINES")


def common_options(f):
    """--iterations --optimizer --gradient --seed --quiet."""
    opts = [
        click.option("--iterations", type=int, default=None, help="optimiser iterations (overrides the scene)"),
        click.option("--optimizer", type=click.Choice(OPTIMIZERS), default=None,
                     help="auto: the most probable past (CMA-ES + Levenberg-Marquardt); or one local "
                          "optimiser with restarts (overrides the scene)"),
        click.option("--gradient", type=click.Choice(GRADIENTS), default=None,
                     help="gradient mode (overrides the scene)"),
        click.option("--seed", type=int, default=None, help="random seed (overrides the scene)"),
        click.option("--quiet", "-q", is_flag=True, help="no progress bar"),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def backend_options(*, with_compile: bool = False):
    """--backend --engine (and with ``with_compile``: --compile), handed to the command as one ``backend``
    argument: ``dejaview.backends.BackendOptions``, checked (a bad combination is a usage error
    naming it). The command passes it on without reading it."""

    def decorate(f):
        @functools.wraps(f)
        def command(*args, backend, engine, use_compile=False, **kwargs):
            from dejaview.backends import BackendOptions, get_backend
            from dejaview.errors import DejaViewError

            get_backend(backend)  # one that cannot run here: its DejaViewError, not a usage error
            try:
                chosen = BackendOptions.of(backend, engine=None if engine == "auto" else engine,
                                           compile=True if use_compile else None)
            except DejaViewError as exc:
                raise click.BadParameter(str(exc)) from None
            return f(*args, backend=chosen, **kwargs)

        opts = [
            click.option("--backend", type=BACKENDS, default="spheres", show_default=True,
                         help="physics backend (warp: pip install 'dejaview[warp]')"),
            click.option("--engine", type=ENGINES, default="auto", show_default=True,
                         help="spheres backend: native C++ simulator (auto: where float64 allows) or torch"),
        ]
        if with_compile:
            opts.append(click.option("--compile", "use_compile", is_flag=True,
                                     help="torch.compile the torch engine's rollouts (the native engine "
                                          "needs no compile)"))
        for opt in reversed(opts):
            command = opt(command)
        return command

    return decorate


def _prepend_package_path(ctx, param, folders) -> None:
    """Put the folders first in ``DEJAVIEW_PACKAGE_PATH``, where ``dejaview.geometry.packages.resolve_package``
    looks (and worker processes, which inherit the environment)."""
    if folders:
        variable = "DEJAVIEW_PACKAGE_PATH"  # dejaview.geometry.packages.PACKAGE_PATH_VARIABLES[0]
        rest = [f for f in os.environ.get(variable, "").split(os.pathsep) if f]
        os.environ[variable] = os.pathsep.join([os.path.abspath(f) for f in folders] + rest)


package_path_option = click.option(
    "--package-path", multiple=True, metavar="DIR", expose_value=False, callback=_prepend_package_path,
    type=click.Path(file_okay=False), help="a folder that holds the packages robots' package://NAME/... "
    "URIs name, searched before DEJAVIEW_PACKAGE_PATH and ROS_PACKAGE_PATH (may be repeated)")
"""``--package-path DIR``: the command's robots find ``package://`` URIs there too."""


def show_progress(quiet: bool) -> bool:
    """Progress bars only on a terminal and without --quiet."""
    return not quiet and sys.stderr.isatty()


def configure_torch() -> None:
    """Set torch's intra-op threads from ``DEJAVIEW_THREADS`` (default 1).

    A rollout is thousands of small ops: one thread avoids OpenMP hand-offs
    that cost more than the work (``docs/benchmarks.md``).
    Large batches (heatmaps) may profit from more: set DEJAVIEW_THREADS=2.
    """
    import os

    import torch

    threads = int(os.environ.get("DEJAVIEW_THREADS", "1"))
    if threads > 0:
        torch.set_num_threads(threads)
