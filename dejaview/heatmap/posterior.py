"""The start-position heatmap as the posterior's marginal: sample the posterior, histogram it.

``posterior_heatmap(scene)`` runs the most-probable-past search and the
posterior sampler of ``dejaview.inference`` (``solve(scene, samples=N)``, with
N = ``<heatmap samples>`` per cell, so a 16 x 16 grid at 4 samples per cell
draws 1024 samples) and histograms the samples' start positions over the start
area's x-y cells (``posterior_report.position_histogram``). Each cell's value
is the posterior probability that the source started in it; the likelihood is
``<observation>``'s (``<heatmap sigma>`` is its position sigma when
``<observation>`` is absent, as the spec says).

Why the sampler and not the per-cell optimisation heatmap (``dejaview.heatmap.search``,
kept for backends without residual Jacobians and for a local optimiser named
explicitly): its cells weigh one optimum each by a hand-tuned basin level,
which is not a probability; the sampler's marginal is, and the calibration
bench (``dejaview bench calibration``) checks it.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import torch

from dejaview.errors import InferenceError, ResourceError

METHODS = ("posterior", "basins")
"""``compute_heatmap`` methods: the posterior's marginal (this module) or the per-cell
optimisations with basin weighting (``dejaview.heatmap.search``)."""
SEARCH_SHARE = 0.5
"""Share of the progress bar's cells given to the search (the sampler gets the rest)."""


def choose_method(method: str | None, optimizer: str | None, backend: str | None) -> str:
    """The heatmap method: ``method`` if given, else ``basins`` where a local optimiser is named or
    the backend has no residual Jacobians (``warp``), else ``posterior``.

    Raises:
        InferenceError: an unknown method, or a local optimiser named with ``posterior``.
    """
    from dejaview.scene.model import OPTIMIZERS

    local_optimizers = [o for o in OPTIMIZERS if o != "auto"]
    if optimizer is not None and optimizer not in OPTIMIZERS:
        raise InferenceError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    if method is None:
        local = optimizer in local_optimizers or (backend not in (None, "spheres"))
        return "basins" if local else "posterior"
    if method not in METHODS:
        raise InferenceError(f"unknown heatmap method {method!r}; choose one of {', '.join(METHODS)}")
    if method == "posterior" and optimizer in local_optimizers:
        raise InferenceError(f"the posterior heatmap samples around the default search's modes; "
                             f"optimizer {optimizer} applies to the basins method")
    if method == "posterior" and backend not in (None, "spheres"):
        raise InferenceError(f"the posterior heatmap needs the spheres backend's residual Jacobians, "
                             f"not {backend}: use method basins")
    return method


def posterior_heatmap(scene, *, cells=None, samples=None, sigma=None, iterations=None, seed=None,
                      callback=None, should_stop=None, problem=None, backend=None, memory_limit=None,
                      amortised=None):
    """Heatmap of the posterior's start-position marginal (module docstring).

    Args:
        scene: Scene (or path) with ``<inference>`` and a ``<start-area>`` with x and y extent.
        cells, samples: override ``<heatmap>`` (defaults 16 x 16, 4 samples per cell).
        sigma: the observation's position sigma (m; overrides ``<observation sigma>`` and
            ``<heatmap sigma>``).
        iterations, seed: the search's (default: the scene's).
        callback: called with a ``HeatmapProgress`` (``cells_done`` of ``cells_total`` tells how
            far the whole run is; ``phase`` search, refine or sample).
        should_stop: polled between iterations and sampler moves; True raises InferenceError.
        problem: reuse a spheres problem of this scene; backend: else the spheres backend's
            ``BackendOptions`` (e.g. its engine) or None.
        memory_limit: bytes the process may hold (None: ``dejaview.memory.limit()``).
        amortised: an amortised posterior (model or file) drawing the samples (``solve --amortised``).
    Returns:
        HeatmapResult (``best``: the solve, with its posterior samples).
    """
    from dejaview.heatmap.result import HeatmapProgress, HeatmapResult
    from dejaview.inference import solve
    from dejaview.inference.solve import SolveParams
    from dejaview.inference.posterior_report import position_histogram
    from dejaview.scene import HeatmapSettings, Observation, Scene

    t0 = time.perf_counter()
    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    inf = scene.inference
    if inf is None:
        raise InferenceError("the scene has no <inference> section: no source to place on a heatmap")
    area = inf.start_area
    if area is None:
        raise InferenceError("a heatmap needs <start-area> in <inference>: the cells cover its x-y extent")
    if not (area.max[0] > area.min[0] and area.max[1] > area.min[1]):
        raise InferenceError("the start area has no x and y extent to cover with a heatmap")
    if not inf.optimize.position:
        raise InferenceError("a heatmap places the start position, but <optimize position> is false")
    hs = inf.heatmap or HeatmapSettings()
    nx, ny = cells if cells is not None else hs.cells
    per_cell = hs.samples if samples is None else samples
    for name, value in (("cells", nx), ("cells", ny), ("samples", per_cell)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise InferenceError(f"heatmap {name} must be positive integers, got {value!r}")
    if sigma is not None:
        if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
            raise InferenceError(f"heatmap sigma must be a positive number, got {sigma!r}")
        obs = replace(inf.observation or Observation(), sigma=float(sigma))
        scene = replace(scene, inference=replace(inf, observation=obs))
    n = per_cell * nx * ny
    total_iterations = iterations if iterations is not None else inf.iterations
    cells_total = nx * ny

    def progress(p):
        if callback is None:
            return
        if p.phase == "sample":
            share = SEARCH_SHARE + (1 - SEARCH_SHARE) * (p.fraction or 0.0)
        else:
            share = SEARCH_SHARE * min(1.0, (p.iteration + 1) / max(total_iterations, 1))
        callback(HeatmapProgress(iteration=p.iteration, loss=p.loss, best_loss=p.best_loss,
                                 elapsed_s=time.perf_counter() - t0, cells_done=int(share * cells_total),
                                 cells_total=cells_total, chunk=0, chunks=1, phase=p.phase))

    try:
        result = solve(scene, SolveParams(optimizer="auto", iterations=iterations, seed=seed, samples=n,
                       memory_limit=memory_limit, amortised=amortised), callback=progress, should_stop=should_stop,
                       problem=problem, backend=backend)
    except ResourceError as exc:
        raise exc.naming(f"a heatmap of {nx} x {ny} cells with {per_cell} samples each ({n} posterior "
                         f"samples)") from None
    if result.posterior is None:
        raise InferenceError("stopped before the posterior was sampled: no heatmap to report")
    layout = result.problem.layout
    with torch.no_grad():
        positions = layout.decode(result.posterior.x.to(layout.base_position.dtype))["position"]
    lo = (float(area.min[0]), float(area.min[1]))
    hi = (float(area.max[0]), float(area.max[1]))
    p = position_histogram(positions, result.posterior.weights, lo, hi, (nx, ny))
    summary = result.settings["posterior"]
    solutions = [{"probability": m["probability"], "neg_log_posterior": m["neg_log_posterior"],
                  "initial_state": m["initial_state"]} for m in summary["modes"]]
    settings = {"method": "posterior", "optimizer": "auto", "iterations": result.settings["iterations"],
                "seed": result.settings["seed"], "backend": result.problem.backend, "cells": [nx, ny],
                "samples": per_cell, "posterior_samples": n,
                "sigma": result.settings["observation"]["sigma"], "agreement": summary.get("agreement"),
                "warnings": list(result.settings.get("warnings", [])),
                **({"amortised": result.settings["amortised"]} if "amortised" in result.settings else {})}
    return HeatmapResult(scene=scene, lo=lo, hi=hi, cells=(nx, ny), probability=p, solutions=solutions,
                         candidates=n, best=result, settings=settings, seconds=time.perf_counter() - t0)


def credible_area(probability, level: float = 0.9) -> float:
    """Fraction of the cells in the smallest set holding ``level`` of the probability (the most
    probable cells first): the area of the ``level`` credible region, as a share of the start area."""
    import numpy as np

    p = np.sort(np.asarray(probability, dtype=float).reshape(-1))[::-1]
    k = int(np.searchsorted(np.cumsum(p), level * p.sum() - 1e-12)) + 1
    return min(k, p.size) / p.size
