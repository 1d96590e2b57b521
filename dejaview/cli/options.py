"""Options shared by the simulate, solve and heatmap commands (scene-format spec, "Command line")."""

from __future__ import annotations

import sys

import click

from dejaview.scene.model import OPTIMIZERS  # a leaf module: --help stays cheap

BACKENDS = ("spheres", "warp")  # dejaview.backends.BACKENDS (not imported: --help stays cheap)
ENGINES = ("auto", "native", "torch")  # dejaview.sim.native.ENGINES


def common_options(f):
    """--backend --engine --iterations --optimizer --gradient --seed --quiet."""
    opts = [
        click.option("--backend", type=click.Choice(BACKENDS), default="spheres", show_default=True,
                     help="physics backend (warp: pip install 'dejaview[warp]')"),
        click.option("--engine", type=click.Choice(ENGINES), default="auto", show_default=True,
                     help="spheres backend: native C++ simulator (auto: where float64 allows) or torch"),
        click.option("--iterations", type=int, default=None, help="optimiser iterations (overrides the scene)"),
        click.option("--optimizer", type=click.Choice(OPTIMIZERS), default=None,
                     help="auto: the most probable past (CMA-ES + Levenberg-Marquardt); or one local "
                          "optimiser with restarts (overrides the scene)"),
        click.option("--gradient", type=click.Choice(["forward", "reverse"]), default=None,
                     help="gradient mode (overrides the scene)"),
        click.option("--seed", type=int, default=None, help="random seed (overrides the scene)"),
        click.option("--quiet", "-q", is_flag=True, help="no progress bar"),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


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
