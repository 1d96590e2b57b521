"""``dejaview.solve``: infer the source's initial state from a scene, and write the results."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dejaview.errors import InferenceError
from dejaview.inference.optimize import OPTIMIZERS, Progress, optimize
from dejaview.inference.problem import objective_to_loss
from dejaview.inference.result import SolveResult

SCREEN_BATCH = 64
"""Candidates per batch while screening (bounds memory; batching amortises the per-op overhead)."""
SCREEN_NEAR = 0.0
"""Default fraction of the first screening round drawn near the scene's own guess
(``screen_guesses``). 0: near draws rank high together, so the best start and the restarts
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
    without autograd, which costs a fraction of a loss + gradient per candidate
    (docs/benchmarks.md, "Simulator"), so screening a few hundred draws costs a
    handful of gradient evaluations and
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
    graph to store, P tangents in one batched pass). On the torch engine, eager
    forward-mode AD pays Python decompositions for every op with a constant
    operand (a World tensor, a Python number: its zero tangent is sized through
    ``torch._refs``), so reverse mode is faster there, and on the native engine
    the adjoint reverse pass is (numbers: ``docs/benchmarks.md``, "Forward-mode
    cost on the torch engine" and the engine benchmarks). Reverse mode is
    therefore the default for every size; forward mode stays available
    (``gradient="forward"``) and gives the same gradients.
    """
    del num_params
    return "reverse"


LOCAL_ONLY = ("multistart", "screen", "screen_rounds", "screen_near", "epsilon", "patience", "lr", "gradient",
              "x0")
"""Settings of the local optimisers with restarts (``gd|adam|lbfgs|bfgs``) that the default search
(``auto``) has no use for: given with ``auto`` they are an error, not silently ignored."""


@dataclass(frozen=True)
class SolveSettings:
    """Everything a solve runs with, resolved once from the scene and the overrides.

    The API (``solve``), the CLI and the service build it through ``SolveSettings.resolve``, so
    they share its defaults and its one-line errors.

    Attributes:
        optimizer: ``auto`` (the search of ``dejaview.inference.search``) or a local optimiser.
        iterations, seed, tolerance: budget, seed, early stop (scene loss in metres).
        budget: rollouts of the ``auto`` search (``search.DEFAULT_BUDGET``).
        gradient, lr, multistart, screen, screen_rounds, screen_near, epsilon, patience: the local
            optimisers' settings (``optimize``).
        posterior: ``PosteriorSettings`` (prior and observation noise).
        samples: posterior samples to draw after the search (0: the most probable start alone).
    """

    optimizer: str
    iterations: int
    seed: int
    tolerance: float | None = None
    budget: int | None = None
    gradient: str | None = None
    lr: float | None = None
    multistart: int = 1
    screen: int = 0
    screen_rounds: int = 1
    screen_near: float = SCREEN_NEAR
    epsilon: float = 0.0
    patience: int = 25
    posterior: object = None
    samples: int = 0

    @staticmethod
    def resolve(scene, *, optimizer: str | None = None, iterations: int | None = None,
                seed: int | None = None, tolerance: float | None = None, budget: int | None = None,
                samples: int | None = None, **local) -> "SolveSettings":
        """Settings from the scene's ``<inference>`` and overrides (None: the scene's / default).

        Args:
            scene: a Scene with an ``<inference>`` section.
            samples: posterior samples (None: the scene's ``<posterior samples>``, else 0).
            local: ``LOCAL_ONLY`` overrides (None: unset).
        Raises:
            InferenceError: one line naming a bad value, or a local optimiser's setting given with
                the ``auto`` search.
        """
        from dejaview.inference.posterior import PosteriorSettings
        from dejaview.scene.model import OPTIMIZERS

        inf = scene.inference
        if inf is None:
            raise InferenceError("the scene has no <inference> section: nothing to solve")
        unknown = set(local) - set(LOCAL_ONLY)
        if unknown:
            raise InferenceError(f"unknown solve setting {sorted(unknown)[0]!r}")
        optimizer = inf.optimizer if optimizer is None else optimizer
        if optimizer not in OPTIMIZERS:
            raise InferenceError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
        iterations = inf.iterations if iterations is None else iterations
        _check_count(iterations, "iterations", 1)
        seed = inf.seed if seed is None else seed
        _check_count(seed, "seed", 0)
        if tolerance is not None and not (isinstance(tolerance, (int, float)) and math.isfinite(tolerance)
                                          and tolerance >= 0):
            raise InferenceError(f"tolerance must be a non-negative number, got {tolerance!r}")
        given = {k: v for k, v in local.items() if v is not None}
        if samples is None:
            samples = inf.posterior.samples if inf.posterior is not None else 0
        _check_count(samples, "samples", 0)
        if samples and optimizer != "auto":
            raise InferenceError("posterior samples need the default search (optimizer auto): the "
                                 "sampler starts from the modes it finds")
        if optimizer == "auto":
            if given:
                name = sorted(given)[0]
                raise InferenceError(f"{name} applies to the local optimisers (gd, adam, lbfgs, bfgs), "
                                     f"not to the default search: drop it or choose an optimizer")
            if budget is not None:
                _check_count(budget, "budget", 1)
            return SolveSettings(optimizer=optimizer, iterations=iterations, seed=seed,
                                 tolerance=tolerance, budget=budget, gradient="reverse",
                                 posterior=PosteriorSettings.from_scene(scene), samples=samples)
        if budget is not None:
            raise InferenceError("budget applies to the default search (optimizer auto)")
        exploration = inf.exploration
        multistart = given.get("multistart", 1)
        _check_count(multistart, "multistart", 1)
        screen = given.get("screen", 0)
        _check_count(screen, "screen", 0)
        screen_rounds = given.get("screen_rounds", 1)
        _check_count(screen_rounds, "screen rounds", 1)
        screen_near = given.get("screen_near", SCREEN_NEAR)
        if not 0.0 <= screen_near <= 1.0:
            raise InferenceError(f"screen_near must be a fraction in [0, 1], got {screen_near!r}")
        gradient = given.get("gradient", inf.gradient)
        if gradient is not None and gradient not in ("forward", "reverse"):
            raise InferenceError(f"unknown gradient mode {gradient!r}; choose forward or reverse")
        return SolveSettings(
            optimizer=optimizer, iterations=iterations, seed=seed, tolerance=tolerance,
            gradient=gradient, lr=given.get("lr"), multistart=multistart, screen=screen,
            screen_rounds=screen_rounds, screen_near=screen_near,
            epsilon=given.get("epsilon", exploration.epsilon if exploration else 0.0),
            patience=given.get("patience", exploration.patience if exploration else 25))


def solve(scene, *, iterations: int | None = None, optimizer: str | None = None,
          gradient: str | None = None, seed: int | None = None, lr: float | None = None,
          multistart: int | None = None, epsilon: float | None = None, patience: int | None = None,
          callback=None, should_stop=None, world=None, problem=None,
          x0: torch.Tensor | None = None, tolerance: float | None = None,
          backend=None,
          screen: int | None = None, screen_rounds: int | None = None,
          screen_near: float | None = None, budget: int | None = None,
          samples: int | None = None, truth: dict | None = None,
          memory_limit: int | None = None) -> SolveResult:
    """Infer the initial state of the scene's source object: its most probable past.

    The default (``optimizer="auto"``, what a scene without ``optimizer`` asks for) maximises the
    posterior of ``dejaview.inference.posterior`` (the scene's ``<prior>`` and ``<observation>``)
    with the search of ``dejaview.inference.search`` (CMA-ES, then Levenberg-Marquardt on exact
    Jacobians). ``gd|adam|lbfgs|bfgs`` run one local optimiser on ``0.5 * loss^2`` with
    epsilon-greedy restarts (``dejaview.inference.optimize``), as the original work did.

    Args:
        scene: a Scene (or a path to a scene file) with an ``<inference>`` section.
        iterations, optimizer, seed, tolerance: override the scene's settings (``SolveSettings``).
        budget: rollouts of the ``auto`` search.
        samples: posterior samples drawn around the search's modes (``dejaview.inference.sampling``;
            None: the scene's ``<posterior samples>``, else none); the result's ``posterior``.
        truth: a known true ``initial_state`` (a ``.truth.json``'s): the result says where it lies
            in the posterior (``posterior_report.truth_report``: its -log posterior, and with
            samples its credible level); the default search only.
        gradient, lr, multistart, epsilon, patience, screen, screen_rounds, screen_near, x0: the
            local optimisers' settings (see ``optimize`` and ``screen_rounds_ranked``):
            multistart K guesses as one batch, ``screen`` random guesses ranked by loss first.
        callback: called with a ``Progress`` after every iteration.
        should_stop: polled every iteration; True stops early (cancellation).
        world / problem: reuse an already built World (spheres) / problem (any backend's,
            ``dejaview.backends.make_problem``, or a bare ``InferenceProblem``).
        backend: a backend's name, ``spheres`` (default) | ``warp``, or ``BackendOptions`` (a
            backend with its own settings: the spheres backend's engine and compile, Warp's
            integrator, ...; ``dejaview.backends``); not with ``problem``. The ``auto`` search
            needs the spheres backend's residual Jacobians; with another backend ``auto`` runs
            ``lbfgs``.
        memory_limit: bytes the process may hold (None: ``dejaview.memory.limit()``); posterior
            samples that would not fit are refused before the search runs.
    Returns:
        SolveResult.
    Raises:
        InferenceError: bad settings (one line naming the problem); ``StartAreaError`` (an
            ``InferenceError``) first of all where the start area cannot hold the source
            (``dejaview.inference.start_area``). ``ResourceError``: posterior samples that would
            need more memory than the limit (``dejaview.memory``), before anything runs.
    """
    from dejaview.scene import Scene

    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    from dejaview.inference.problem import check_inference
    from dejaview.inference.sizing import check_solve_memory
    from dejaview.inference.start_area import check_start_area

    local = dict(multistart=multistart, screen=screen, screen_rounds=screen_rounds,
                 screen_near=screen_near, epsilon=epsilon, patience=patience, lr=lr, gradient=gradient,
                 x0=x0)
    check_inference(scene)
    collision = check_start_area(scene)  # before anything is built or simulated
    problem = _make_problem(scene, problem, world, backend)
    if (optimizer or scene.inference.optimizer) == "auto" and problem.backend != "spheres":
        optimizer = "lbfgs"  # the default search needs the spheres backend's residual Jacobians
    settings = SolveSettings.resolve(scene, optimizer=optimizer, iterations=iterations, seed=seed,
                                     tolerance=tolerance, budget=budget, samples=samples, **local)
    mu = scene.inference.model_uncertainty
    if settings.optimizer != "auto" and mu is not None and ((mu.friction or 0) > 0 or (mu.restitution or 0) > 0):
        raise InferenceError(f"<model-uncertainty> needs the default search (optimizer auto on the spheres "
                             f"backend), not optimizer {settings.optimizer} on {problem.backend}")
    samples_drawn = None
    if settings.optimizer == "auto":
        if settings.samples:
            collision = check_solve_memory(scene, problem, settings.samples, collision, memory_limit)
        opt, extra, post = _search(scene, problem, settings, callback, should_stop, collision)
        if settings.samples and not opt.stopped and math.isfinite(opt.loss):
            samples_drawn = _sample(post, opt, settings, callback, should_stop)
            from dejaview.inference.posterior_report import summary

            extra["posterior"] = summary(samples_drawn, problem.layout, opt.modes)
        if truth is not None and not opt.stopped:
            from dejaview.inference.posterior_report import truth_report

            intervals = extra["posterior"]["intervals"] if "posterior" in extra else None
            extra["truth"] = truth_report(post, samples_drawn, problem.layout, truth, intervals)
    else:
        if truth is not None:
            raise InferenceError("a truth is placed in the posterior of the default search (optimizer auto)")
        opt, extra = _optimize_locally(problem, settings, x0, callback, should_stop)
    if not math.isfinite(opt.loss):
        if opt.stopped and not opt.history:
            raise InferenceError("stopped before the first iteration: no solution to report")
        raise InferenceError("every evaluation gave a non-finite loss: check the scene's numbers")
    best = opt.x.unsqueeze(0).to(problem.dtype)
    with torch.no_grad():
        decoded = {k: v[0].tolist() for k, v in problem.layout.decode(best).items()}
        traj = problem.simulate(best, steps=problem.duration_steps, record_every=1)
    rest, warnings = _rest_report(scene, problem, settings, best, samples_drawn)
    info = {"optimizer": settings.optimizer, "gradient": settings.gradient, "iterations": settings.iterations,
            "seed": settings.seed, "backend": problem.backend, **extra, "rest": rest,
            "warnings": warnings + extra.get("warnings", [])}
    return SolveResult(scene=scene, problem=problem, optimization=opt, initial_state=decoded,
                       loss=opt.loss, trajectory=traj, settings=info, posterior=samples_drawn)


def _rest_report(scene, problem, settings: SolveSettings, best: torch.Tensor, samples) -> tuple[dict, list[str]]:
    """When the answer came to rest, and warnings where it (or a sample) is still moving at the end
    of a scene that saw the source lying still (``dejaview.inference.rest``)."""
    from dejaview.inference.posterior import PosteriorSettings
    from dejaview.inference.rest import duration_warnings

    post = settings.posterior if settings.posterior is not None else PosteriorSettings.from_scene(scene)
    return duration_warnings(problem, post, best, samples)


def _make_problem(scene, problem, world, backend):
    """The backend problem of a solve: ``problem`` itself, or built from ``backend`` (a name or
    ``BackendOptions``) and ``world``."""
    from dejaview.backends import BackendOptions, as_problem
    from dejaview.inference.problem import check_inference

    check_inference(scene)
    if problem is not None:
        if backend is not None:
            raise InferenceError("backend options build a problem; solve got a built problem as well: "
                                 "pass one of backend and problem")
        return as_problem(problem)
    options = BackendOptions.of(backend)
    return options.make_problem(scene, **({} if world is None else {"world": world}))


def _search(scene, problem, settings: SolveSettings, callback, should_stop, collision=None):
    """The default search: the most probable start under the scene's prior and observation noise
    (``collision``: the scene's ``SceneCollision``, if one was built already)."""
    from dejaview.inference.model_uncertainty import ModelVariants, refine_under_variants
    from dejaview.inference.posterior import Posterior, feasibility_check
    from dejaview.inference.search import DEFAULT_BUDGET, LM_FINAL_ITERATIONS, staged_search

    inner = getattr(problem, "inner", problem)
    feasible = feasibility_check(scene, inner, collision=collision)
    post = Posterior(inner, settings.posterior, feasible=feasible)
    opt = staged_search(post, iterations=settings.iterations, seed=settings.seed, callback=callback,
                        should_stop=should_stop, tolerance=settings.tolerance,
                        budget=settings.budget or DEFAULT_BUDGET)
    model = ModelVariants.from_scene(scene, inner.world)
    if model is not None and not opt.stopped:  # the modes refined and ranked under model uncertainty
        post = Posterior(inner, settings.posterior, feasible=feasible, model=model)
        opt = refine_under_variants(post, opt, iterations=LM_FINAL_ITERATIONS, seed=settings.seed,
                                    callback=callback, should_stop=should_stop)
    extra = {**settings.posterior.to_json(), **({"model_uncertainty": model.to_json()} if model else {}),
             "search": {
        "neg_log_posterior": opt.cost, "observation_chi2": opt.chi2, "rollouts": opt.rollouts,
        "jacobians": opt.jacobians, "budget": settings.budget or DEFAULT_BUDGET,
        "modes": [{"neg_log_posterior": m.cost, "observation_chi2": m.chi2, "loss": m.loss,
                   **({} if m.heldout is None else {"heldout_neg_log_posterior": m.heldout,
                                                    "heldout_mean_end_chi2": m.heldout_mean_chi2}),
                   "initial_state": {k: v[0].tolist() for k, v in
                                     problem.layout.decode(m.x.unsqueeze(0).to(problem.dtype)).items()}}
                  for m in opt.modes]}}
    return opt, extra, post


def _sample(post, opt, settings: SolveSettings, callback, should_stop):
    """Posterior samples around the search's modes, reporting progress as phase ``sample``."""
    from dejaview.inference.sampling import sample_posterior

    last = opt.history[-1] if opt.history else None
    it = last.iteration if last is not None else 0

    def report(d):
        if callback is not None:
            callback(Progress(iteration=it, loss=opt.cost, best_loss=opt.cost, duration_s=0.0,
                              elapsed_s=(last.elapsed_s if last else 0.0) + d["elapsed_s"], restarted=False,
                              evaluations=post.rollouts, phase="sample", fraction=d["fraction"]))
    return sample_posterior(post, opt.modes, settings.samples, seed=settings.seed, callback=report,
                            should_stop=should_stop)


def _optimize_locally(problem, settings: SolveSettings, x0, callback, should_stop):
    """A local optimiser with epsilon-greedy restarts from screened or given guesses."""
    gradient = settings.gradient or default_gradient(problem.num_params)
    if gradient not in problem.gradient_modes:
        raise InferenceError(f"the {problem.backend} backend offers {' and '.join(problem.gradient_modes)}-mode "
                             f"gradients only, not {gradient} mode; use --gradient reverse")
    s = settings
    gen = torch.Generator().manual_seed(int(s.seed))
    sample = problem.layout.sample
    screened = 0
    if x0 is None:
        x0 = problem.layout.encode().to(problem.dtype)
        if s.screen > 0:
            ranked, _, drawn = screen_rounds_ranked(problem, x0, max(s.screen, s.multistart - 1), gen,
                                                    should_stop=should_stop, rounds=s.screen_rounds,
                                                    near=s.screen_near)
            screened = ranked.shape[0]
            x0, pool = ranked[:s.multistart], restart_pool(ranked[s.multistart:], drawn[s.multistart:])

            def sample(n, generator):
                """Restarts: the next-best screened guesses, then fresh draws."""
                taken = [pool.pop(0) for _ in range(min(n, len(pool)))]
                parts = [torch.stack(taken)] if taken else []
                if n > len(taken):
                    parts.append(problem.layout.sample(n - len(taken), generator).to(x0.dtype))
                return torch.cat(parts, 0)
        elif s.multistart > 1:
            x0 = torch.cat([x0, problem.layout.sample(s.multistart - 1, gen)], 0)
    x0 = x0.to(problem.dtype)
    opt = optimize(problem.objective_and_grad, x0, optimizer=s.optimizer, iterations=s.iterations,
                   gradient=gradient, lr=s.lr, epsilon=s.epsilon, patience=s.patience, sample=sample,
                   seed=s.seed, callback=callback, should_stop=should_stop, tolerance=s.tolerance,
                   report=objective_to_loss)
    return opt, {"gradient": gradient, "multistart": s.multistart, "epsilon": s.epsilon,
                 "patience": s.patience, "screened": screened}
