"""``compute_heatmap``: where could the source have started?

The x-y extent of ``<start-area>`` is cut into ``cells`` = nx x ny cells. In
each cell ``samples`` optimisations run, with the start position free inside
that cell only (the sigmoid reparameterisation of ``ParameterLayout`` with
per-candidate boxes; z keeps the start area's range) and different initial
guesses: sample 0 starts at the cell centre with the scene's own guess of
orientation and velocities, the others at a random point of the cell with a
random orientation (where free) and random velocities (uniform in balls of
``max_speed`` m/s and ``max_spin`` rad/s).

Every candidate of every cell is one row of a batch: the cells are taken in
chunks of ``batch_size`` candidates, and each chunk is a single batched
optimisation (``dejaview.inference.optimize``; the candidates' objectives are
independent, so their sum has a block-diagonal Hessian). Adam (the default
here) and GD step each candidate exactly as if it ran alone; L-BFGS/BFGS on a
chunk share one line search and curvature history and are offered but not
recommended. A chunk's best-per-candidate parameters are its solutions.

The solutions are then deduplicated within each cell, their basins measured
by batched perturbed rollouts (no gradients), and weighted into cell
probabilities: see ``dejaview.heatmap.weighting`` for the formula.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import torch

from dejaview.errors import InferenceError
from dejaview.heatmap.result import HeatmapProgress, HeatmapResult

DEFAULT_OPTIMIZER = "adam"
DEFAULT_ADAM_LR = 0.1
"""Adam's step here: positions are logits of a cell (not of the whole area), so a cell is
crossed in a few dozen steps; twice the solver's default."""
DEFAULT_RADII = (0.01, 0.02, 0.05, 0.1, 0.2)
"""Robustness radii in m/s of initial linear velocity (ascending)."""
DEFAULT_DIRECTIONS = 8
SPIN_PER_SPEED = 5.0
"""rad/s of angular-velocity perturbation per m/s of linear (the parameter scales' ratio)."""


def cell_boxes(lo: torch.Tensor, hi: torch.Tensor, nx: int, ny: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Boxes of the nx x ny cells of a start area, cell c = j * nx + i.

    Args:
        lo, hi: (3,) start-area corners.
    Returns:
        (C, 3) lower and upper corners (z keeps the area's range).
    """
    ii = torch.arange(nx, dtype=lo.dtype)
    jj = torch.arange(ny, dtype=lo.dtype)
    dx = (hi[0] - lo[0]) / nx
    dy = (hi[1] - lo[1]) / ny
    x0 = (lo[0] + ii * dx).repeat(ny)
    y0 = (lo[1] + jj * dy).repeat_interleave(nx)
    c = nx * ny
    low = torch.stack([x0, y0, lo[2].expand(c)], -1)
    high = torch.stack([x0 + dx, y0 + dy, hi[2].expand(c)], -1)
    return low, high


def split_cells(num_cells: int, samples: int, batch_size: int, workers: int = 1) -> list[list[int]]:
    """Cells in chunks of whole cells, at most ``batch_size`` candidates each, and at least
    ``workers`` chunks (when there are that many cells) so every worker has one."""
    per = max(1, batch_size // samples)
    n = max(-(-num_cells // per), min(workers, num_cells))
    bounds = [round(i * num_cells / n) for i in range(n + 1)]
    return [list(range(bounds[i], bounds[i + 1])) for i in range(n)]


def compute_heatmap(scene, *, cells: tuple[int, int] | None = None, samples: int | None = None,
                    sigma: float | None = None, iterations: int | None = None,
                    optimizer: str | None = None, gradient: str | None = None,
                    seed: int | None = None, lr: float | None = None, batch_size: int = 1024,
                    workers: int = 1,
                    radii: tuple[float, ...] = DEFAULT_RADII, directions: int = DEFAULT_DIRECTIONS,
                    velocity_tol: float = 0.05, spin_tol: float = 0.5, position_tol: float = 0.02,
                    callback=None, should_stop=None, problem=None, backend=None,
                    method: str | None = None, ray: str | None = None,
                    memory_limit: int | None = None, amortised=None) -> HeatmapResult:
    """Start-position heatmap of a scene's source.

    ``method="posterior"`` (the default where the spheres backend runs, no local optimiser is
    named and no ``ray``; ``dejaview.heatmap.posterior.choose_method``) samples the posterior and
    histograms the samples' start positions (``dejaview.heatmap.posterior``): the cells'
    probabilities are the posterior's marginal. Of the arguments below it takes cells, samples (per
    cell), sigma (the observation's), iterations and seed (the search's), callback, should_stop,
    problem, backend. ``method="basins"`` runs the per-cell optimisations of this module's docstring.

    The steps: the settings (``_settings``), the problem (``_with_problem``), every chunk's
    first guesses (``_first_guesses``), the batched optimisations (``_optimise_chunks``), the
    solutions deduplicated (``_candidates``), their basins (``_robustness``), the weighting
    (``_weigh``) and the best solution re-simulated (``_best_solution``).

    Args:
        scene: Scene (or path) with ``<inference>`` and a ``<start-area>`` with x and y extent.
        cells, samples, sigma: override ``<heatmap>`` (defaults 16 x 16, 4, 0.02).
        iterations: optimiser iterations per candidate (default: the scene's).
        optimizer: default ``adam`` (independent per candidate in a batch, lr
            ``DEFAULT_ADAM_LR``); gradient: the scene's or reverse.
        seed: seeds the guesses and the perturbation directions.
        lr: learning rate (default per optimiser).
        batch_size: candidates per batched optimisation (whole cells per chunk). Rollouts of
            small bodies are bound by per-op overhead, so one large batch is much cheaper than
            several small ones; memory grows with it.
        workers: processes optimising chunks at once (1: in this process). Threads do not
            help (the per-op Python overhead holds the GIL); each worker process is spawned
            and rebuilds the problem from the scene with the backend's options (a few seconds),
            so use them for large grids. The cells are
            split into at least this many chunks.
        radii, directions: robustness perturbations (m/s, ascending; directions per radius).
        velocity_tol, spin_tol, position_tol: deduplication tolerances.
        callback: called with a ``HeatmapProgress`` after every iteration.
        should_stop: polled every iteration; True stops the run (raises InferenceError).
        problem: reuse a problem of this scene (``dejaview.backends``; a bare SpheresProblem is
            wrapped).
        backend: a backend's name (``spheres``, the default, | ``warp``) or ``BackendOptions``
            (with its own settings, e.g. the spheres backend's engine; ``dejaview.backends``); not
            with ``problem``. Worker processes and Ray actors rebuild the problem from it.
        method: ``posterior`` | ``basins`` | None (above).
        ray: optimise the chunks on Ray (``dejaview.parallel``): ``"local"`` or a cluster address,
            ``workers`` actors; each builds the problem from the scene. Same results as in processes.
            Basins method only (a ``ray`` given picks it).
        amortised: an amortised posterior (``AmortisedModel`` or its file) answering the posterior
            heatmap's samples (``solve --amortised``); posterior method only.
        memory_limit: bytes the process may hold (None: ``dejaview.memory.limit()``): the posterior
            method refuses samples that would need more, before any work (``ResourceError``).
    Returns:
        HeatmapResult.
    Raises:
        InferenceError: no start area with x-y extent, bad settings, stopped, or nothing finite;
            ``StartAreaError`` before any work where the start area cannot hold the source
            (``dejaview.inference.start_area``; the posterior method through ``solve``).
    """
    from dejaview.backends import BackendOptions, as_problem
    from dejaview.heatmap.posterior import choose_method, posterior_heatmap
    from dejaview.heatmap.weighting import deduplicate
    from dejaview.inference.start_area import check_start_area

    if problem is not None and backend is not None:
        raise InferenceError("backend options build a problem; the heatmap got a built problem as well: "
                             "pass one of backend and problem")
    # the options workers rebuild the problem from (a reused problem's own: its engine)
    options = BackendOptions.of(backend) if problem is None else as_problem(problem).backend_options()
    if ray is not None and method is None:
        method = "basins"  # Ray distributes the per-cell optimisations' chunks
    if choose_method(method, optimizer, options.name) == "posterior":
        if ray is not None:
            raise InferenceError("ray distributes the basins heatmap's chunks; the posterior heatmap runs "
                                 "in this process: drop ray or use method basins")
        for name, value in (("lr", lr), ("gradient", gradient)):
            if value is not None:
                raise InferenceError(f"{name} applies to the basins heatmap (per-cell optimisations), "
                                     f"not to the posterior's")
        return posterior_heatmap(scene, cells=cells, samples=samples, sigma=sigma, iterations=iterations,
                                 seed=seed, callback=callback, should_stop=should_stop, problem=problem,
                                 backend=None if problem is not None else options, memory_limit=memory_limit,
                                 amortised=amortised)
    if amortised is not None:
        raise InferenceError("an amortised posterior answers the posterior heatmap (method posterior), not the "
                             "basins heatmap")
    if getattr(scene, "inference", None) is not None and scene.inference.infers_physics:
        raise InferenceError("<physics-prior> needs the posterior heatmap (method posterior): the basins "
                             "heatmap's per-cell optimisations have no prior to hold the physics to")
    t_start = time.perf_counter()
    run = _settings(scene, cells, samples, sigma, iterations, optimizer, seed, batch_size, workers,
                    radii, directions)
    check_start_area(run.scene)  # before anything is built or optimised
    run = replace(_with_problem(run, problem, options, gradient, lr), ray=ray)
    gen = torch.Generator().manual_seed(int(run.seed))
    guesses = _first_guesses(run, gen)
    results, history, state = _optimise_chunks(run, guesses, options, callback, should_stop, t_start)
    cand = _candidates(run, guesses, results)
    keep = deduplicate(cand.cell, cand.loss, cand.start, velocity_tol=velocity_tol, spin_tol=spin_tol,
                       position_tol=position_tol)
    tick = _robustness_ticks(run, callback, state["best"], state["iteration"], t_start)
    level = _robustness(run, cand, keep, gen, should_stop, tick)
    p, solutions = _weigh(run, cand, keep, level)
    settings = {"optimizer": run.optimizer, "gradient": run.gradient, "iterations": run.iterations,
                "seed": run.seed, "backend": run.problem.backend, "sigma": run.sigma, "samples": run.samples,
                "cells": [run.nx, run.ny], "radii": list(run.radii), "directions": run.directions,
                "batch_size": run.batch_size, "velocity_tol": velocity_tol, "spin_tol": spin_tol,
                "position_tol": position_tol}
    best = _best_solution(run, cand, history, settings)
    layout = run.layout
    lo2 = (float(layout.lo[0]), float(layout.lo[1]))
    hi2 = (float(layout.hi[0]), float(layout.hi[1]))
    return HeatmapResult(scene=run.scene, lo=lo2, hi=hi2, cells=(run.nx, run.ny),
                         probability=p.reshape(run.ny, run.nx).numpy(), solutions=solutions,
                         candidates=int(cand.cell.numel()), best=best, settings=settings,
                         seconds=time.perf_counter() - t_start)


@dataclass
class _HeatmapRun:
    """The resolved settings of one ``compute_heatmap`` run, and (``_with_problem``) its problem."""

    scene: object
    nx: int
    ny: int
    samples: int
    sigma: float
    iterations: int
    optimizer: str
    seed: int
    batch_size: int
    workers: int
    radii: tuple[float, ...]
    directions: int
    chunks: list[list[int]]
    problem: object = None
    gradient: str | None = None
    lr: float | None = None
    ray: str | None = None

    @property
    def num_cells(self) -> int:
        return self.nx * self.ny

    @property
    def layout(self):
        return self.problem.layout

    @property
    def dtype(self) -> torch.dtype:
        return self.problem.dtype


@dataclass
class _Candidates:
    """Every candidate's outcome, all chunks in order: cell (N,), parameters x (N, P), loss (N,),
    its cell box lo, hi (N, 3) and the decoded start state (name -> (N, ...))."""

    cell: torch.Tensor
    x: torch.Tensor
    loss: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    start: dict


def _settings(scene, cells, samples, sigma, iterations, optimizer, seed, batch_size, workers,
              radii, directions) -> _HeatmapRun:
    """The scene (read from a path) and ``compute_heatmap``'s settings with the scene's defaults,
    checked (one-line ``InferenceError`` naming the first bad one)."""
    from dejaview.inference.optimize import OPTIMIZERS
    from dejaview.scene import HeatmapSettings, Scene

    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    inf = scene.inference
    if inf is None:
        raise InferenceError("the scene has no <inference> section: no source to place on a heatmap")
    hs = inf.heatmap or HeatmapSettings()
    nx, ny = cells if cells is not None else hs.cells
    samples = hs.samples if samples is None else samples
    sigma = hs.sigma if sigma is None else sigma
    iterations = inf.iterations if iterations is None else iterations
    optimizer = DEFAULT_OPTIMIZER if optimizer in (None, "auto") else optimizer
    seed = inf.seed if seed is None else seed
    for name, value in (("cells", nx), ("cells", ny), ("samples", samples), ("iterations", iterations),
                        ("batch_size", batch_size), ("directions", directions), ("workers", workers)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise InferenceError(f"heatmap {name} must be positive integers, got {value!r}")
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
        raise InferenceError(f"heatmap sigma must be a positive number, got {sigma!r}")
    if optimizer not in OPTIMIZERS:
        raise InferenceError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    if not radii or any(r <= 0 for r in radii) or list(radii) != sorted(radii):
        raise InferenceError(f"robustness radii must be positive and ascending, got {radii!r}")
    if inf.start_area is None:
        raise InferenceError("a heatmap needs <start-area> in <inference>: the cells cover its x-y extent")
    return _HeatmapRun(scene=scene, nx=nx, ny=ny, samples=samples, sigma=sigma, iterations=iterations,
                optimizer=optimizer, seed=seed, batch_size=batch_size, workers=workers, radii=radii,
                directions=directions, chunks=split_cells(nx * ny, samples, batch_size, workers))


def _with_problem(run: _HeatmapRun, problem, options, gradient: str | None, lr: float | None) -> _HeatmapRun:
    """``run`` with its problem (``problem`` reused, or built from ``BackendOptions`` ``options``),
    gradient mode and learning rate, checked."""
    from dejaview.backends import as_problem
    from dejaview.inference.local import default_gradient

    problem = (as_problem(problem) if problem is not None
               else options.make_problem(run.scene))
    layout = problem.layout
    if not layout.free["position"] or 0 not in layout.position_axes or 1 not in layout.position_axes:
        raise InferenceError("a heatmap needs the start position free with x and y extent in <start-area> "
                             "(min < max in x and in y, and <optimize position='true'>)")
    gradient = gradient or run.scene.inference.gradient or default_gradient(problem.num_params)
    if lr is None and run.optimizer == "adam":
        lr = DEFAULT_ADAM_LR
    if gradient not in ("forward", "reverse"):
        raise InferenceError(f"unknown gradient mode {gradient!r}; choose forward or reverse")
    if gradient not in problem.gradient_modes:
        raise InferenceError(f"the {problem.backend} backend offers {' and '.join(problem.gradient_modes)}"
                             f"-mode gradients only, not {gradient} mode")
    return replace(run, problem=problem, gradient=gradient, lr=lr)


def _first_guesses(run: _HeatmapRun, gen: torch.Generator) -> list[tuple[torch.Tensor, object, torch.Tensor]]:
    """Per chunk: (cell of each candidate (K,), the chunk's layout (per-candidate cell boxes),
    first guesses x0 (K, P)). Sample 0 of a cell starts at its centre with the scene's own guess
    of orientation and velocities, the others at random."""
    layout, dtype, samples = run.layout, run.dtype, run.samples
    cell_lo, cell_hi = cell_boxes(layout.lo, layout.hi, run.nx, run.ny)
    # the scene's own guess of orientation and velocities, at the cell centre (logit 0)
    given = layout.encode().to(dtype)
    n_pos = len(layout.position_axes)
    given[:, :n_pos] = 0.0
    # every chunk's first guesses drawn here, in order, so results do not depend on the workers
    guesses = []
    for chunk in run.chunks:
        idx = torch.tensor(chunk, dtype=torch.long).repeat_interleave(samples)
        k = idx.numel()
        chunk_layout = replace(layout, lo=cell_lo[idx], hi=cell_hi[idx])
        x0 = chunk_layout.sample(k, gen).to(dtype)
        first = torch.arange(k) % samples == 0
        x0[first] = given.expand(int(first.sum()), -1)
        guesses.append((idx, chunk_layout, x0))
    return guesses


def _optimise_chunks(run: _HeatmapRun, guesses: list, options, callback, should_stop,
                     t_start: float) -> tuple[list, list, dict]:
    """Optimise every chunk (in this process, in ``run.workers`` processes or on Ray, which build
    their problem from ``options``, ``BackendOptions``), reporting progress.

    Returns:
        (per chunk (candidate_x (K, P), candidate_loss (K,), stopped), history (one ``Progress``
        per iteration over all chunks), {"iteration": iterations run, "best": best loss, ...}).
    Raises:
        InferenceError: ``should_stop`` ended the run.
    """
    chunks, num_cells = run.chunks, run.num_cells
    history = []
    state = {"iteration": 0, "best": math.inf, "cells_done": 0}

    def progress(ci, p):
        state["best"] = min(state["best"], p.best_loss)
        hp = HeatmapProgress(iteration=state["iteration"], loss=p.loss, best_loss=state["best"],
                             elapsed_s=time.perf_counter() - t_start, cells_done=state["cells_done"],
                             cells_total=num_cells, chunk=ci, chunks=len(chunks))
        state["iteration"] += 1
        history.append(replace(p, iteration=hp.iteration, best_loss=state["best"]))
        if callback is not None:
            callback(hp)

    opts = dict(optimizer=run.optimizer, iterations=run.iterations, gradient=run.gradient, lr=run.lr,
                seed=run.seed)
    problem = run.problem
    if run.ray is not None or (run.workers > 1 and len(chunks) > 1):
        results = _chunks_in_processes(run.scene, options, guesses, opts, run.workers, progress, should_stop,
                                       state, chunks, run.ray)
    else:
        results = []
        for ci, (idx, chunk_layout, x0) in enumerate(guesses):
            results.append(optimise_chunk(with_layout(problem, chunk_layout), x0, ci, opts,
                                          lambda p, _ci=ci: progress(_ci, p), should_stop))
            if results[-1][2]:
                break
            state["cells_done"] += len(chunks[ci])
    if any(stopped for _, _, stopped in results) or len(results) < len(chunks):
        raise InferenceError(f"heatmap stopped after {state['cells_done']} of {num_cells} cells")
    return results, history, state


def _candidates(run: _HeatmapRun, guesses: list, results: list) -> _Candidates:
    """All chunks' outcomes as one batch, their start states decoded; raises ``InferenceError``
    when no loss is finite."""
    outcomes = [(g[0], r[0], r[1], g[1].lo, g[1].hi) for g, r in zip(guesses, results)]
    all_cell, all_x, all_loss, all_lo, all_hi = (list(v) for v in zip(*outcomes))
    cell = torch.cat(all_cell)
    xs = torch.cat(all_x)
    loss = torch.cat(all_loss).to(run.dtype)
    lo_all, hi_all = torch.cat(all_lo), torch.cat(all_hi)
    if not torch.isfinite(loss).any():
        raise InferenceError("every heatmap candidate gave a non-finite loss: check the scene's numbers")
    full_layout = replace(run.layout, lo=lo_all, hi=hi_all)
    with torch.no_grad():
        start = {k_: v.detach() for k_, v in full_layout.decode(xs).items()}
    return _Candidates(cell=cell, x=xs, loss=loss, lo=lo_all, hi=hi_all, start=start)


def _robustness_ticks(run: _HeatmapRun, callback, best_loss: float, iteration: int, t_start: float):
    """A function reporting one robustness batch to ``callback`` (iterations counted on from
    ``iteration``), or None without a callback."""
    if callback is None:
        return None
    count = [iteration]
    chunks = len(run.chunks)

    def tick():
        callback(HeatmapProgress(iteration=count[0], loss=math.nan, best_loss=best_loss,
                                 elapsed_s=time.perf_counter() - t_start,
                                 cells_done=run.num_cells, cells_total=run.num_cells,
                                 chunk=chunks - 1, chunks=chunks, phase="robustness"))
        count[0] += 1

    return tick


def _robustness(run: _HeatmapRun, cand: _Candidates, keep: torch.Tensor, gen: torch.Generator, should_stop,
                tick) -> torch.Tensor:
    """Robustness levels (len(keep),) long of the kept solutions: perturbed rollouts of those the
    Gaussian does not already rule out (loss <= 3 sigma; level 0 for the others). ``tick``: called
    after every batch of rollouts (or None)."""
    from dejaview.heatmap.weighting import perturbation_directions, robustness_levels

    layout, dtype, radii, directions, sigma = run.layout, run.dtype, run.radii, run.directions, run.sigma
    loss = cand.loss
    level = torch.zeros(keep.numel(), dtype=torch.long)
    worth = (loss[keep] <= 3.0 * sigma).nonzero().flatten()
    if not worth.numel():
        return level
    spin = layout.free["angular_velocity"]
    sel = keep[worth]
    dirs = perturbation_directions(sel.numel(), directions, spin, gen, dtype)  # (M, D, 6)
    rad = torch.tensor(radii, dtype=dtype)
    off = rad[None, :, None, None] * dirs[:, None]  # (M, R, D, 6): m/s, then rad/s per SPIN_PER_SPEED
    m, r, d = sel.numel(), len(radii), directions
    rows = m * r * d
    rep = lambda t: t[sel].repeat_interleave(r * d, 0)  # noqa: E731
    rob_layout = replace(layout, free={**layout.free, "linear_velocity": True, "angular_velocity": True},
                         lo=rep(cand.lo), hi=rep(cand.hi))
    x_rob = state_parameters(rob_layout, rep(cand.x), layout,
                             rep(cand.start["linear_velocity"]) + off[..., :3].reshape(rows, 3),
                             rep(cand.start["angular_velocity"]) + SPIN_PER_SPEED * off[..., 3:].reshape(rows, 3))
    perturbed = torch.empty(rows, dtype=dtype)
    step = max(run.batch_size, 1) * 4
    with torch.no_grad():
        for a in range(0, rows, step):
            if should_stop is not None and should_stop():
                raise InferenceError("heatmap stopped while measuring basins")
            part = with_layout(run.problem, replace(rob_layout, lo=rob_layout.lo[a:a + step],
                                                    hi=rob_layout.hi[a:a + step]))
            perturbed[a:a + step] = part.loss(x_rob[a:a + step])
            if tick is not None:
                tick()
    level[worth] = robustness_levels(loss[sel], perturbed.reshape(m, r, d), sigma)
    return level


def _weigh(run: _HeatmapRun, cand: _Candidates, keep: torch.Tensor, level: torch.Tensor) -> tuple[torch.Tensor, list]:
    """(cell probabilities (C,), one dict per kept solution) from the kept solutions' losses and
    robustness levels (``dejaview.heatmap.weighting``)."""
    from dejaview.heatmap.weighting import cell_probability, log_weights

    cell, loss = cand.cell, cand.loss
    logw = log_weights(loss[keep], level, len(run.radii), run.sigma)
    p = cell_probability(cell[keep], logw, run.num_cells)
    weight = torch.exp(logw - torch.logsumexp(logw, 0))
    solutions = []
    for n, i in enumerate(keep.tolist()):
        c = int(cell[i])
        solutions.append({"cell": [c % run.nx, c // run.nx], "loss": float(loss[i]), "level": int(level[n]),
                          "weight": float(weight[n]),
                          "initial_state": {k_: v[i].tolist() for k_, v in cand.start.items()}})
    return p, solutions


def _best_solution(run: _HeatmapRun, cand: _Candidates, history: list, settings: dict):
    """The best candidate overall, re-simulated, as a ``SolveResult``."""
    from dejaview.inference.optimize import OptimizationResult
    from dejaview.inference.result import SolveResult

    loss, xs = cand.loss, cand.x
    b = int(torch.argmin(torch.where(torch.isfinite(loss), loss, torch.full_like(loss, math.inf))))
    best_problem = with_layout(run.problem, replace(run.layout, lo=cand.lo[b:b + 1], hi=cand.hi[b:b + 1]))
    with torch.no_grad():
        traj = best_problem.simulate(xs[b:b + 1], steps=run.problem.duration_steps, record_every=1)
    optres = OptimizationResult(x=xs[b], loss=float(loss[b]), history=history, best_index=b)
    return SolveResult(scene=run.scene, problem=best_problem, optimization=optres,
                       initial_state={k_: v[b].tolist() for k_, v in cand.start.items()}, loss=float(loss[b]),
                       trajectory=traj, settings=settings)


def optimise_chunk(problem, x0: torch.Tensor, ci: int, opts: dict, callback, should_stop):
    """One chunk's batched optimisation: (candidate_x (K, P), candidate_loss (K,), stopped)."""
    from dejaview.inference.optimize import optimize
    from dejaview.backends.base import objective_to_loss

    opt = optimize(problem.objective_and_grad, x0, optimizer=opts["optimizer"], iterations=opts["iterations"],
                   gradient=opts["gradient"], lr=opts["lr"], epsilon=0.0, callback=callback,
                   should_stop=should_stop, report=objective_to_loss, seed=opts["seed"] + ci)
    return opt.candidate_x, opt.candidate_loss, opt.stopped


def _worker_init(scene, options):
    """A worker's setup (``dejaview.parallel``): one thread (torch's and the native simulator's),
    the scene's problem built once per worker."""
    import os

    torch.set_num_threads(1)
    os.environ["DEJAVIEW_NATIVE_THREADS"] = "1"
    return options.make_problem(scene)


def _worker_chunk(problem, item, report, stopped):
    ci, lo, hi, x0, opts = item
    chunk = with_layout(problem, replace(problem.layout, lo=lo, hi=hi))
    return optimise_chunk(chunk, x0, ci, opts, report, stopped)


def _chunks_in_processes(scene, options, guesses, opts, workers, progress, should_stop, state,
                         chunks, ray=None):
    """Optimise the chunks in ``workers`` spawned processes or Ray actors (``dejaview.parallel``; each
    builds the problem from the scene once); progress is reported from this thread."""
    from dejaview.parallel import map_chunks

    def done(ci, _result):
        state["cells_done"] += len(chunks[ci])

    items = [(ci, layout.lo, layout.hi, x0, opts) for ci, (_, layout, x0) in enumerate(guesses)]
    return map_chunks(_worker_chunk, items, setup=_worker_init, setup_args=(scene, options),
                      workers=workers, ray=ray, on_report=progress, on_done=done, should_stop=should_stop)


def with_layout(problem, layout):
    """A problem like ``problem`` (``dejaview.backends`` interface) with another parameter layout,
    leaving ``problem`` untouched."""
    import copy

    out = copy.copy(problem)
    out.layout = layout
    return out


def state_parameters(target, x: torch.Tensor, source, linear: torch.Tensor, angular: torch.Tensor) -> torch.Tensor:
    """Parameters (B, P') of layout ``target`` (``source`` with both velocity blocks free) for the
    start of parameters x (B, P) of layout ``source`` with the given velocities (B, 3) m/s, rad/s."""
    parts, i = [], 0
    if source.free["position"]:
        a = len(source.position_axes)
        parts.append(x[:, i:i + a])
        i += a
    if source.free["orientation"]:
        parts.append(x[:, i:i + 3])
        i += 3
    parts.append(linear / target.scale["linear_velocity"])
    parts.append(angular / target.scale["angular_velocity"])
    return torch.cat(parts, -1)
