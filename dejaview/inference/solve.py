"""``dejaview.solve``: infer the source's initial state from a scene, and write the results."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch

from dejaview.errors import InferenceError
from dejaview.inference.optimize import OPTIMIZERS, OptimizationResult, Progress, optimize
from dejaview.inference.problem import objective_to_loss
from dejaview.sim.integrate import Trajectory

SCREEN_BATCH = 64
"""Candidates per batch while screening (bounds memory; batching amortises the per-op overhead)."""
SCREEN_NEAR = 0.0
"""Default fraction of the first screening round drawn near the scene's own guess
(``screen_guesses``). 0: measured on the recovery suite, 0.5 solved the upright-mug case that
prior-only screening never did (mug_off_counter-2) but lost three others (mug_off_counter-0 and -1,
box_along_shelf-0): the near draws rank high together, so the best start and the restarts
after it all tell one story, and the search loses the diversity of the prior."""
SCREEN_SIGMA = 1.0
"""Standard deviation of those draws in scaled parameters (0.1 m / 0.5 rad / 1 m/s / 5 rad/s by
default; positions in the start area's logit coordinates)."""


def _check_count(value, what: str, minimum: int) -> None:
    """One-line error unless ``value`` is an int (not a bool) of at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        kind = "positive" if minimum == 1 else "non-negative"
        raise InferenceError(f"{what} must be a {kind} integer, got {value!r}")


def screen_guesses(problem, first: torch.Tensor, count: int, generator: torch.Generator,
                   should_stop=None, batch: int = SCREEN_BATCH, rounds: int = 1,
                   elite: int | None = None, near: float = SCREEN_NEAR,
                   sigma: float = SCREEN_SIGMA) -> tuple[torch.Tensor, torch.Tensor]:
    """Rank initial guesses by their loss, without gradients (a cheap global step).

    The guesses and losses of ``screen_rounds_ranked`` (same arguments), without the round
    each guess came from.
    """
    x, loss, _ = screen_rounds_ranked(problem, first, count, generator, should_stop=should_stop,
                                      batch=batch, rounds=rounds, elite=elite, near=near,
                                      sigma=sigma)
    return x, loss


def screen_rounds_ranked(problem, first: torch.Tensor, count: int, generator: torch.Generator,
                         should_stop=None, batch: int = SCREEN_BATCH, rounds: int = 1,
                         elite: int | None = None, near: float = SCREEN_NEAR,
                         sigma: float = SCREEN_SIGMA
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rank initial guesses by their loss, without gradients, and say which round drew each.

    The guesses are ``first`` plus ``count`` random draws: a fraction ``1 - near``
    from the whole prior (``problem.layout.sample``: start area, any orientation,
    velocities in the layout's bounds) and a fraction ``near`` around the scene's
    own guess ``first[0]`` (normal, standard deviation ``sigma`` in the scaled
    parameters). The scene's guess is the user's prior (a mug upright on the
    counter), and the prior alone almost never comes near it: its rotation
    vectors fill the ball of radius pi uniformly, so one lies within 30 degrees
    of the given orientation with probability (1/6)^3 = 0.5 %, and 64 draws hold
    a third of a guess that starts upright; the solver would then only try pasts
    that start tumbling. The guesses are simulated in batches of ``batch``
    without autograd: on the mug scene one batched rollout costs ~0.3 s per
    candidate against ~4.5 s for one loss + gradient at B = 1 (eager), so
    screening a few hundred draws costs a handful of gradient evaluations and
    moves the start into the right basin where the scene's guess tells a
    different story.

    ``rounds > 1`` refines the ranking by the cross-entropy method: each further
    round draws ``count`` guesses from a normal distribution (diagonal, in the
    scaled parameters) fitted to the ``elite`` best guesses so far (default
    ``max(4, count // 8)``), so the search narrows onto the most promising basin
    where the loss is flat or kinked and a gradient step would not get far.

    Args:
        problem: a backend problem (``loss(x) -> (K,)``).
        first: (F, P) guesses that always take part (the scene's own).
        count: number of random draws per round.
        generator: seeds the draws.
        should_stop: polled between batches; True ends screening with what was ranked.
        rounds: 1 + the number of cross-entropy refinements.
        elite: guesses the refinements fit their distribution to.
        near: fraction of the first round's draws around ``first[0]`` (0: all from the prior).
        sigma: their standard deviation (scaled parameters).
    Returns:
        guesses (M, P) sorted by loss (best first; non-finite losses last), their losses (M,)
        and the round that drew each (M,) (0: the first round, with ``first``).
    """
    _check_count(rounds, "screen rounds", 1)
    elite = max(4, count // 8) if elite is None else int(elite)
    guesses, losses, drawn_in = [], [], []
    stopped = False
    for r in range(rounds):
        if r == 0:
            n_near = int(round(count * near))
            x = torch.cat([first, problem.layout.sample(count - n_near, generator).to(first.dtype),
                           first[:1] + sigma * torch.randn(n_near, first.shape[1], generator=generator,
                                                           dtype=first.dtype)], 0)
        else:
            loss = torch.cat(losses)
            keep = torch.argsort(loss, stable=True)[:elite]
            best = torch.cat(guesses)[keep[torch.isfinite(loss[keep])]]
            if best.shape[0] < 2:
                break
            mean, std = best.mean(0), best.std(0).clamp_min(1e-3)
            x = mean + std * torch.randn(count, first.shape[1], generator=generator, dtype=first.dtype)
        with torch.no_grad():
            for chunk in x.split(batch):
                if guesses and should_stop is not None and should_stop():
                    stopped = True
                    break
                value = problem.loss(chunk).detach().to(first.dtype)
                guesses.append(chunk)
                drawn_in.append(torch.full((chunk.shape[0],), r, dtype=torch.long))
                losses.append(torch.where(torch.isfinite(value), value, torch.full_like(value, math.inf)))
        if stopped:
            break
    x, loss, drawn = torch.cat(guesses), torch.cat(losses), torch.cat(drawn_in)
    order = torch.argsort(loss, stable=True)
    return x[order], loss[order], drawn[order]


def restart_pool(ranked: torch.Tensor, drawn: torch.Tensor) -> list[torch.Tensor]:
    """The order in which restarts take screened guesses that were not used as starts.

    Restarts explore, so the first round's guesses (drawn over the whole prior) come first,
    best first; the refinement rounds' guesses follow. Those crowd around the best guess,
    i.e. around the start, where the optimiser's own hops (``optimize``) already search.

    Args:
        ranked: (M, P) guesses sorted by loss (``screen_rounds_ranked``).
        drawn: (M,) the round that drew each.
    Returns:
        M guesses (P,), in the order restarts take them.
    """
    return list(ranked[drawn == 0]) + list(ranked[drawn > 0])


def default_gradient(num_params: int) -> str:
    """The faster gradient mode for a problem (scene format: ``gradient`` defaults to it).

    In principle forward mode wins for the ~12 parameters of one object (no
    graph to store, P tangents in one batched pass). Measured with torch 2.13
    on CPU, eager forward-mode AD costs ~40x a plain op per op (Python
    decompositions behind ``torch.func.jvp``), so one gradient of 12
    parameters takes ~20x a plain rollout in forward mode and ~4x in reverse
    mode (bench/sim.py: 61 s vs 12.8 s on the reference mug scene). Reverse mode is therefore the default for
    every size; forward mode stays available (``gradient="forward"``) and
    gives the same gradients.

    Why (measured, torch 2.13 CPU, one thread): an op between a tangent-carrying
    tensor and a constant (a World tensor, a Python number) gives the constant
    a zero tangent (an "efficient zero tensor"), whose kernels size their
    output through the Python meta registrations (``torch._refs``): ``x * c``
    costs ~1.5 ms under ``torch.func.jvp`` against ~80 us for ``x * x`` and
    ~20 us without AD; plain ``torch.autograd.forward_ad`` dual tensors behave
    the same (1.7 ms, 60 us with ``c`` made dual). Nearly every op of a step
    has a constant operand.
    """
    del num_params
    return "reverse"


@dataclass
class SolveResult:
    """Outcome of ``solve``.

    Attributes:
        scene: the scene solved.
        problem: the backend's problem (``dejaview.backends``; ``SpheresProblem`` wraps an
            ``InferenceProblem``).
        optimization: the raw OptimizationResult.
        initial_state: dict of the best initial state (object-frame position, orientation,
            linear_velocity, angular_velocity) as lists.
        loss: best loss.
        trajectory: the best solution re-simulated (record every step), batch of 1.
        settings: optimizer, gradient, iterations, seed, backend.
    """

    scene: object
    problem: object
    optimization: OptimizationResult
    initial_state: dict
    loss: float
    trajectory: Trajectory
    settings: dict = field(default_factory=dict)

    @property
    def iterations(self) -> list[Progress]:
        return self.optimization.history

    def final_pose(self) -> tuple[list[float], list[float]]:
        """Object-frame position and orientation of the source at the end of the trajectory."""
        return self.problem.final_pose(self.trajectory)

    def to_json(self) -> dict:
        """``result.json`` content (scene-format spec, "Outputs")."""
        end_pos, end_q = self.final_pose()
        return {
            "source": self.scene.inference.source,
            "backend": self.settings.get("backend", self.problem.backend),
            "optimizer": self.settings["optimizer"],
            "gradient": self.settings["gradient"],
            "loss": self.loss,
            "initial_state": self.initial_state,
            "final_pose": {"position": end_pos, "orientation": end_q},
            "target": {"position": list(self.scene.inference.target.position),
                       "orientation": list(self.scene.inference.target.orientation)},
            "loss_kind": self.problem.loss_kind,
            "evaluate": self.problem.evaluate,
            "seed": self.settings.get("seed", 0),
            "multistart": self.settings.get("multistart", 1),
            "screened": self.settings.get("screened", 0),
            "parameters": self.problem.layout.names(),
            "simulation": self.problem.simulation_settings(),
            "stopped_early": self.optimization.stopped,
            "iterations": [{"iteration": p.iteration, "loss": _num(p.loss), "best_loss": _num(p.best_loss),
                            "duration_s": p.duration_s, "restarted": p.restarted}
                           for p in self.iterations],
        }

    def write(self, out_dir, plot: bool = False) -> dict[str, Path]:
        """Write result.json, iterations.csv, trajectory.csv (and loss.png with ``plot``)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {"result": out / "result.json", "iterations": out / "iterations.csv",
                 "trajectory": out / "trajectory.csv"}
        paths["result"].write_text(json.dumps(self.to_json(), indent=2), encoding="utf-8")
        with open(paths["iterations"], "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(["iteration", "loss", "best_loss", "duration_s", "restarted"])
            for p in self.iterations:
                writer.writerow([p.iteration, f"{p.loss:.9g}", f"{p.best_loss:.9g}",
                                 f"{p.duration_s:.6f}", int(p.restarted)])
        self.problem.write_trajectory(paths["trajectory"], self.trajectory)
        if plot:
            paths["plot"] = plot_losses(self.iterations, out / "loss.png")
        return paths


def _num(v: float):
    return v if math.isfinite(v) else None


def plot_losses(history: list[Progress], path) -> Path:
    """loss.png: loss and best loss per iteration (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    its = [p.iteration for p in history]
    ax.semilogy(its, [max(p.loss, 1e-12) for p in history], lw=1, alpha=0.6, label="loss")
    ax.semilogy(its, [max(p.best_loss, 1e-12) for p in history], lw=2, label="best loss")
    for p in history:
        if p.restarted:
            ax.axvline(p.iteration, color="grey", lw=0.5, ls=":")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def _check_engine(engine: str, compile: bool) -> str:
    from dejaview.sim.native import ENGINES

    if engine not in ENGINES:
        raise InferenceError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
    if compile and engine == "native":
        raise InferenceError("compile applies to the torch engine; the native engine is compiled C++ "
                             "already: drop --compile or choose --engine torch")
    return engine


def solve(scene, *, iterations: int | None = None, optimizer: str | None = None,
          gradient: str | None = None, seed: int | None = None, lr: float | None = None,
          multistart: int = 1, epsilon: float | None = None, patience: int | None = None,
          callback=None, should_stop=None, world=None, problem=None,
          x0: torch.Tensor | None = None, tolerance: float | None = None,
          compile: bool = False, backend: str | None = None, engine: str | None = None,
          screen: int = 0,
          screen_rounds: int = 1, screen_near: float = SCREEN_NEAR) -> SolveResult:
    """Infer the initial state of the scene's source object.

    Args:
        scene: a Scene (or a path to a scene file) with an ``<inference>`` section.
        iterations, optimizer, gradient, seed: override the scene's settings.
        lr: learning rate (default per optimiser).
        multistart: K initial guesses run as one batch (the scene's guess plus K-1 random,
            or the K best screened guesses), each with an optimiser of its own (see
            ``dejaview.inference.optimize``).
        screen: rank the scene's guess and ``screen`` random guesses by their loss
            (``screen_guesses``, no gradients) and start from the best ``multistart``;
            epsilon-greedy restarts then take the next-best screened guesses before
            fresh random draws. 0: no screening.
        screen_rounds: rounds of screening, ``screen`` guesses each; rounds after the first
            draw around the best so far (cross-entropy method, ``screen_guesses``). The run
            starts from the best guess of any round; restarts take the first round's guesses
            before the refinements (those crowd around the start, where the hops search).
        screen_near: fraction of the first round drawn around the scene's guess instead of
            from the whole prior (``screen_guesses``' ``near``; default ``SCREEN_NEAR``).
        epsilon, patience: override ``<exploration>``.
        callback: called with a ``Progress`` after every iteration.
        should_stop: polled every iteration; True stops early (cancellation).
        world / problem: reuse an already built World (spheres) / problem (any backend's,
            ``dejaview.backends.make_problem``, or a bare ``InferenceProblem``).
        x0: (K, P) explicit initial guesses.
        tolerance: stop once the best loss is at or below this.
        compile: compiled rollouts (see ``InferenceProblem.compile``; spheres only).
        backend: ``spheres`` (default) | ``warp`` (``dejaview.backends``); ignored with ``problem``.
        engine: simulation engine of the spheres backend, ``auto`` | ``native`` | ``torch``
            (``InferenceProblem.engine``; None keeps the problem's, by default ``auto``).
    Returns:
        SolveResult.
    Raises:
        InferenceError: bad settings (one line naming the problem).
    """
    from dejaview.backends import as_problem, make_problem
    from dejaview.scene import Scene

    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    inf = scene.inference
    if inf is None:
        raise InferenceError("the scene has no <inference> section: nothing to solve")
    iterations = inf.iterations if iterations is None else iterations
    _check_count(iterations, "iterations", 1)
    optimizer = inf.optimizer if optimizer is None else optimizer
    if optimizer not in OPTIMIZERS:
        raise InferenceError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    if multistart < 1:
        raise InferenceError(f"multistart must be >= 1, got {multistart}")
    _check_count(screen, "screen", 0)
    _check_count(screen_rounds, "screen rounds", 1)
    if not 0.0 <= screen_near <= 1.0:
        raise InferenceError(f"screen_near must be a fraction in [0, 1], got {screen_near!r}")
    seed = inf.seed if seed is None else seed
    if problem is None:
        options = {} if world is None else {"world": world}
        problem = make_problem(scene, backend or "spheres", **options)
    problem = as_problem(problem)
    if problem.backend == "spheres":
        problem.compile = compile
        if engine is not None:
            problem.engine = _check_engine(engine, compile)
    elif compile or engine is not None:
        raise InferenceError(f"{'compile' if compile else 'engine'} is an option of the spheres backend, "
                             f"not of {problem.backend}")
    gradient = gradient or inf.gradient or default_gradient(problem.num_params)
    if gradient not in ("forward", "reverse"):
        raise InferenceError(f"unknown gradient mode {gradient!r}; choose forward or reverse")
    if gradient not in problem.gradient_modes:
        raise InferenceError(f"the {problem.backend} backend offers {' and '.join(problem.gradient_modes)}-mode "
                             f"gradients only, not {gradient} mode; use --gradient reverse")
    exploration = inf.exploration
    eps = epsilon if epsilon is not None else (exploration.epsilon if exploration else 0.0)
    pat = patience if patience is not None else (exploration.patience if exploration else 25)
    gen = torch.Generator().manual_seed(int(seed))
    sample = problem.layout.sample
    screened = 0
    if x0 is None:
        x0 = problem.layout.encode().to(problem.dtype)
        if screen > 0:
            ranked, _, drawn = screen_rounds_ranked(problem, x0, max(screen, multistart - 1), gen,
                                                    should_stop=should_stop, rounds=screen_rounds,
                                                    near=screen_near)
            screened = ranked.shape[0]
            x0, pool = ranked[:multistart], restart_pool(ranked[multistart:], drawn[multistart:])

            def sample(n, generator):
                """Restarts: the next-best screened guesses, then fresh draws."""
                taken = [pool.pop(0) for _ in range(min(n, len(pool)))]
                parts = [torch.stack(taken)] if taken else []
                if n > len(taken):
                    parts.append(problem.layout.sample(n - len(taken), generator).to(x0.dtype))
                return torch.cat(parts, 0)
        elif multistart > 1:
            x0 = torch.cat([x0, problem.layout.sample(multistart - 1, gen)], 0)
    x0 = x0.to(problem.dtype)
    opt = optimize(problem.objective_and_grad, x0, optimizer=optimizer, iterations=iterations,
                   gradient=gradient, lr=lr, epsilon=eps, patience=pat, sample=sample,
                   seed=seed, callback=callback, should_stop=should_stop, tolerance=tolerance,
                   report=objective_to_loss)
    if not math.isfinite(opt.loss):
        if opt.stopped and not opt.history:
            raise InferenceError("stopped before the first iteration: no solution to report")
        raise InferenceError("every evaluation gave a non-finite loss: check the scene's numbers")
    best = opt.x.unsqueeze(0)
    with torch.no_grad():
        decoded = {k: v[0].tolist() for k, v in problem.layout.decode(best).items()}
        traj = problem.simulate(best, steps=problem.duration_steps, record_every=1)
    settings = {"optimizer": optimizer, "gradient": gradient, "iterations": iterations, "seed": seed,
                "backend": problem.backend, "multistart": multistart, "epsilon": eps, "patience": pat,
                "screened": screened}
    return SolveResult(scene=scene, problem=problem, optimization=opt, initial_state=decoded,
                       loss=opt.loss, trajectory=traj, settings=settings)
