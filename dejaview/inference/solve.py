"""``dejaview.solve``: infer the source's initial state from a scene, and write the results."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from dejaview.errors import InferenceError
from dejaview.inference.local import LocalParams, _check_count, fit_locally
from dejaview.inference.optimize import Progress
from dejaview.inference.params import SamplerParams, SearchParams
from dejaview.inference.posterior import Posterior
from dejaview.inference.result import SolveResult
from dejaview.inference.sampling import Sampler
from dejaview.inference.search import MapSearch

LOCAL_ONLY = ("multistart", "screen", "screen_rounds", "screen_near", "epsilon", "patience", "lr", "gradient")
"""Settings of the local optimisers with restarts (``gd|adam|lbfgs|bfgs``) that the default search
(``auto``) has no use for: given with ``auto`` they are an error, not silently ignored."""


@dataclass(frozen=True)
class SolveParams:
    """What a solve changes from its scene's ``<inference>``: each field None keeps the scene's
    value (else the default). Checked against the scene by ``SolveSettings.resolve`` (one-line
    ``InferenceError``s naming the field).

    Attributes:
        optimizer: ``auto`` (``MapSearch``) or ``gd|adam|lbfgs|bfgs`` (``fit_locally``).
        iterations, seed, tolerance: budget, seed, early stop (scene loss in metres).
        budget: rollouts of the ``auto`` search (``SearchParams.budget``).
        samples: posterior samples drawn after the search (``Sampler``; the scene's
            ``<posterior samples>``, else 0).
        gradient, lr, multistart, screen, screen_rounds, screen_near, epsilon, patience: the local
            pipeline's (``LocalParams``); an error with ``auto``.
        memory_limit: bytes a sampled solve may take (``dejaview.memory``; None: the machine's).
        amortised: an amortised posterior (``AmortisedModel`` or the path of its file, ``dejaview
            train``) answering instead of the search and the sampler
            (``dejaview.inference.amortised.answer``).
    """

    optimizer: str | None = None
    iterations: int | None = None
    seed: int | None = None
    tolerance: float | None = None
    budget: int | None = None
    samples: int | None = None
    gradient: str | None = None
    lr: float | None = None
    multistart: int | None = None
    screen: int | None = None
    screen_rounds: int | None = None
    screen_near: float | None = None
    epsilon: float | None = None
    patience: int | None = None
    memory_limit: int | None = None
    amortised: object = None


@dataclass(frozen=True)
class SolveSettings:
    """Everything a solve runs with, resolved once from the scene and the overrides.

    The API (``solve``), the CLI and the service build it through ``SolveSettings.resolve``, so
    they share its defaults and its one-line errors.

    Attributes:
        optimizer: ``auto`` (``MapSearch``) or a local optimiser (``fit_locally``).
        iterations, seed: as resolved (``result.json`` reports them).
        gradient: the gradient mode (``auto``: reverse; a local optimiser's: None for its default).
        search: ``SearchParams`` of the ``auto`` search, else None.
        local: ``LocalParams`` of a local optimiser, else None.
        sampler: ``SamplerParams`` of the posterior sampler.
        posterior: ``PosteriorSettings`` (prior and observation noise) of the ``auto`` search.
        samples: posterior samples to draw after the search (0: the most probable start alone).
        amortised: the ``AmortisedModel`` that answers, or None.
    """

    optimizer: str
    iterations: int
    seed: int
    gradient: str | None
    search: SearchParams | None
    local: LocalParams | None
    sampler: SamplerParams
    posterior: object = None
    samples: int = 0
    amortised: object = None

    @staticmethod
    def resolve(scene, params: SolveParams | None = None) -> "SolveSettings":
        """Settings from the scene's ``<inference>`` and ``params`` (its None fields: the scene's
        value, else the default).

        Raises:
            InferenceError: one line naming a bad value, or a local optimiser's setting given with
                the ``auto`` search.
        """
        from dejaview.inference.posterior import PosteriorSettings
        from dejaview.scene.model import OPTIMIZERS

        inf = scene.inference
        if inf is None:
            raise InferenceError("the scene has no <inference> section: nothing to solve")
        params = SolveParams() if params is None else params
        optimizer, iterations, seed, tolerance = params.optimizer, params.iterations, params.seed, params.tolerance
        budget, samples = params.budget, params.samples
        local = {k: getattr(params, k) for k in LOCAL_ONLY}
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
            search = SearchParams(iterations=iterations, seed=seed, tolerance=tolerance,
                                  **({} if budget is None else {"budget": budget}))
            amortised = params.amortised
            if amortised is not None and not hasattr(amortised, "sample"):
                from dejaview.inference.amortised import AmortisedModel

                amortised = AmortisedModel.load(amortised)
            return SolveSettings(optimizer=optimizer, iterations=iterations, seed=seed, gradient="reverse",
                                 search=search, local=None, sampler=SamplerParams(seed=seed),
                                 posterior=PosteriorSettings.from_scene(scene), samples=samples,
                                 amortised=amortised)
        if params.amortised is not None:
            raise InferenceError(f"an amortised posterior answers in place of the default search (optimizer "
                                 f"auto), not with optimizer {optimizer}")
        if budget is not None:
            raise InferenceError("budget applies to the default search (optimizer auto)")
        exploration = inf.exploration
        multistart = given.get("multistart", 1)
        _check_count(multistart, "multistart", 1)
        screen = given.get("screen", 0)
        _check_count(screen, "screen", 0)
        screen_rounds = given.get("screen_rounds", 1)
        _check_count(screen_rounds, "screen rounds", 1)
        screen_near = given.get("screen_near", LocalParams.screen_near)
        if not 0.0 <= screen_near <= 1.0:
            raise InferenceError(f"screen_near must be a fraction in [0, 1], got {screen_near!r}")
        gradient = given.get("gradient", inf.gradient)
        if gradient is not None and gradient not in ("forward", "reverse"):
            raise InferenceError(f"unknown gradient mode {gradient!r}; choose forward or reverse")
        local = LocalParams(
            optimizer=optimizer, iterations=iterations, seed=seed, tolerance=tolerance,
            gradient=gradient, lr=given.get("lr"), multistart=multistart, screen=screen,
            screen_rounds=screen_rounds, screen_near=screen_near,
            epsilon=given.get("epsilon", exploration.epsilon if exploration else LocalParams.epsilon),
            patience=given.get("patience", exploration.patience if exploration else LocalParams.patience))
        return SolveSettings(optimizer=optimizer, iterations=iterations, seed=seed, gradient=gradient,
                             search=None, local=local, sampler=SamplerParams(seed=seed))


def solve(scene, params: SolveParams | None = None, *, callback=None, should_stop=None, backend=None,
          problem=None, truth: dict | None = None) -> SolveResult:
    """Infer the initial state of the scene's source object: its most probable past.

    The default (``optimizer="auto"``, what a scene without ``optimizer`` asks for) maximises the
    posterior of ``dejaview.inference.posterior`` (the scene's ``<prior>`` and ``<observation>``)
    with the search of ``dejaview.inference.search`` (CMA-ES, then Levenberg-Marquardt on exact
    Jacobians). ``gd|adam|lbfgs|bfgs`` run one local optimiser on ``0.5 * loss^2`` with
    epsilon-greedy restarts (``dejaview.inference.optimize``), as the original work did.

    Args:
        scene: a Scene (or a path to a scene file) with an ``<inference>`` section.
        params: ``SolveParams``: what to change from the scene's ``<inference>`` (iterations,
            optimizer, seed, budget, samples, the local pipeline's settings, the memory limit).
        callback: called with a ``Progress`` after every iteration.
        should_stop: polled every iteration; True stops early (cancellation).
        backend: a backend's name, ``spheres`` (default) | ``warp``, or ``BackendOptions`` (a
            backend with its own settings: the spheres backend's engine and compile, Warp's
            integrator, ...; ``dejaview.backends``); not with ``problem``.
            The ``auto`` search needs the spheres backend's residual Jacobians; with another
            backend ``auto`` runs ``lbfgs``.
        problem: an already built problem (any backend's, ``dejaview.backends.make_problem``).
        truth: a known true ``initial_state`` (a ``.truth.json``'s): the result says where it lies
            in the posterior (``posterior_report.truth_report``: its -log posterior, and with
            samples its credible level); the default search only.
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
    from dejaview.backends.base import check_inference
    from dejaview.inference.sizing import check_solve_memory
    from dejaview.inference.start_area import check_start_area

    params = SolveParams() if params is None else params
    check_inference(scene)
    collision = check_start_area(scene)  # before anything is built or simulated
    problem = _make_problem(scene, problem, backend)
    optimizer = params.optimizer
    if (optimizer or scene.inference.optimizer) == "auto" and problem.backend != "spheres":
        optimizer = "lbfgs"  # the default search needs the spheres backend's residual Jacobians
    settings = SolveSettings.resolve(scene, replace(params, optimizer=optimizer))
    mu = scene.inference.model_uncertainty
    if settings.optimizer != "auto" and mu is not None and ((mu.friction or 0) > 0 or (mu.restitution or 0) > 0):
        raise InferenceError(f"<model-uncertainty> needs the default search (optimizer auto on the spheres "
                             f"backend), not optimizer {settings.optimizer} on {problem.backend}")
    if settings.optimizer != "auto" and scene.inference.infers_physics:
        raise InferenceError(f"<physics-prior> needs the default search (optimizer auto on the spheres backend), "
                             f"not optimizer {settings.optimizer} on {problem.backend}")
    samples_drawn, kde_rows = None, 0
    if settings.optimizer == "auto":
        if settings.samples:
            collision, kde_rows = check_solve_memory(scene, problem, settings.samples, collision,
                                                     params.memory_limit)
        post = Posterior.from_scene(scene, problem=problem, collision=collision)
        search = settings.search
        if settings.amortised is not None:
            from dejaview.inference.amortised.answer import answer

            opt, samples_drawn, amortised = answer(post, settings.amortised, settings.samples, seed=settings.seed,
                                                   search=search, should_stop=should_stop)
            extra = _search_report(post, opt, search, problem.layout)
            extra["amortised"] = amortised
            if not amortised["fitted"]:
                extra["warnings"] = [f"the amortised model does not fit this observation (Pareto k-hat "
                                     f"{amortised['k_hat']:.2f} > {amortised['max_k_hat']}): "
                                     + ("the samples come from the sampler, with the model in its proposal"
                                        if settings.samples else "the most probable start is refined from "
                                        "its best draws; ask for samples to have the sampler check it")]
        else:
            found = opt = MapSearch(search).run(post, callback=callback, should_stop=should_stop)
            if settings.samples and not opt.stopped and math.isfinite(opt.loss):
                samples_drawn = _sample(post, opt, settings, callback, should_stop, kde_rows)
                opt = refine_from_samples(post, opt, samples_drawn, search)
            extra = _search_report(post, opt, search, problem.layout)
            if opt.cost < found.cost:  # a sample, refined, is the answer
                extra["search"]["from_samples"] = {"search_neg_log_posterior": found.cost}
        if samples_drawn is not None:
            from dejaview.inference.posterior_report import summary

            extra["posterior"] = summary(samples_drawn, problem.layout, opt.modes)
        if truth is not None and not opt.stopped:
            from dejaview.inference.posterior_report import truth_report

            intervals = extra["posterior"]["intervals"] if "posterior" in extra else None
            extra["truth"] = truth_report(post, samples_drawn, problem.layout, truth, intervals)
    else:
        if truth is not None:
            raise InferenceError("a truth is placed in the posterior of the default search (optimizer auto)")
        opt, extra = fit_locally(problem, settings.local, callback=callback, should_stop=should_stop)
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
    if getattr(problem.layout, "physics", None) is not None:
        from dejaview.inference.posterior_report import physics_report

        info["physics"] = physics_report(problem.layout, best, extra.get("posterior"))
    return SolveResult(scene=scene, problem=problem, optimization=opt, initial_state=decoded,
                       loss=opt.loss, trajectory=traj, settings=info, posterior=samples_drawn)


def _rest_report(scene, problem, settings: SolveSettings, best: torch.Tensor, samples) -> tuple[dict, list[str]]:
    """When the answer came to rest, and warnings where it (or a sample) is still moving at the end
    of a scene that saw the source lying still (``dejaview.inference.rest``)."""
    from dejaview.inference.posterior import PosteriorSettings
    from dejaview.inference.rest import duration_warnings

    post = settings.posterior if settings.posterior is not None else PosteriorSettings.from_scene(scene)
    return duration_warnings(problem, post, best, samples)


def _make_problem(scene, problem, backend):
    """The backend problem of a solve: ``problem`` itself, or built from ``backend`` (a name or
    ``BackendOptions``)."""
    from dejaview.backends import BackendOptions, as_problem

    if problem is not None:
        if backend is not None:
            raise InferenceError("backend options build a problem; solve got a built problem as well: "
                                 "pass one of backend and problem")
        return as_problem(problem)
    return BackendOptions.of(backend).make_problem(scene)


def _search_report(post, opt, params: SearchParams, layout) -> dict:
    """``result.json``'s prior, noise, model uncertainty and ``search`` of a solve by ``MapSearch``."""
    model = post.model
    return {**post.settings.to_json(), **({"model_uncertainty": model.to_json()} if model else {}),
            "search": {
        "neg_log_posterior": opt.cost, "observation_chi2": opt.chi2, "rollouts": opt.rollouts,
        "jacobians": opt.jacobians, "budget": params.budget,
        "modes": [{"neg_log_posterior": m.cost, "observation_chi2": m.chi2, "loss": m.loss,
                   **({} if m.heldout is None else {"heldout_neg_log_posterior": m.heldout,
                                                    "heldout_mean_end_chi2": m.heldout_mean_chi2}),
                   "initial_state": {k: v[0].tolist() for k, v in
                                     layout.decode(m.x.unsqueeze(0).to(post.problem.dtype)).items()}}
                  for m in opt.modes]}}


def refine_from_samples(post, opt, samples, params: SearchParams, per_run: int = 2):
    """The most probable start, checked against the posterior's samples: the ``per_run`` most
    probable distinct samples of each of the sampler's runs, refined by Levenberg-Marquardt
    (``params.lm_final_iterations``); where one ends more probable than the search's answer (by
    ``params.sample_gain`` nats at least), it is the answer, first among the modes (the samples'
    ``mode_index`` follows).

    Why: the sampler's runs settle in branches of a rugged posterior that the search's stages did
    not reach (measured on box_tossed_tracked, seed 0: the search's answer cost 7.87, a run's best
    sample refined 5.6). Not under model uncertainty, whose modes are ranked on held-out variants
    (``search.refine_under_variants``).

    Returns:
        the ``SearchResult`` (``opt`` itself where no sample did better).
    """
    from dejaview.inference.search import Mode, levenberg_marquardt

    if post.model is not None or opt.stopped or samples is None:
        return opt
    run = samples.run if samples.run is not None else torch.zeros(samples.x.shape[0], dtype=torch.long)
    starts = []
    for r in torch.unique(run).tolist():
        rows = (run == r).nonzero().flatten()
        xs, order = samples.x[rows], torch.argsort(samples.log_density[rows], descending=True)
        picked = []
        for i in order.tolist():
            if all(not torch.equal(xs[i], y) for y in picked):
                picked.append(xs[i])
            if len(picked) == per_run:
                break
        starts += picked
    if not starts:
        return opt
    rollouts0, jacobians0 = post.rollouts, post.jacobians
    x, cost, _, _ = levenberg_marquardt(torch.stack(starts).to(torch.float64), lambda y: post.cost(y)[0],
                                        lambda y, rows: post.jacobian(y), params.lm_final_iterations, tolerance=1e-8)
    best = int(torch.argmin(cost))
    better = float(cost[best]) <= opt.cost - params.sample_gain
    if better:
        _, chi2, loss = post.cost(x[best:best + 1])  # the chosen one's misfit and loss
    spent = {"rollouts": opt.rollouts + post.rollouts - rollouts0, "jacobians": opt.jacobians + post.jacobians - jacobians0}
    if not better:
        return replace(opt, **spent)
    mode = Mode(x[best].clone(), float(cost[best]), float(chi2[0]), float(loss[0]))
    samples.mode_index = [i + 1 for i in samples.mode_index]
    return replace(opt, x=mode.x, loss=mode.loss, cost=mode.cost, chi2=mode.chi2, modes=[mode] + list(opt.modes),
                   **spent)


def _sample(post, opt, settings: SolveSettings, callback, should_stop, kde_rows: int = 0):
    """Posterior samples around the search's modes, reporting progress as phase ``sample``;
    ``kde_rows``: ``SamplerParams.kde_rows`` (``sizing.check_solve_memory``)."""
    last = opt.history[-1] if opt.history else None
    it = last.iteration if last is not None else 0

    def report(d):
        if callback is not None:
            callback(Progress(iteration=it, loss=opt.cost, best_loss=opt.cost, duration_s=0.0,
                              elapsed_s=(last.elapsed_s if last else 0.0) + d["elapsed_s"], restarted=False,
                              evaluations=post.rollouts, phase="sample", fraction=d["fraction"]))
    params = replace(settings.sampler, kde_rows=kde_rows)
    return Sampler(params).sample(post, opt.modes, settings.samples, callback=report, should_stop=should_stop)
