"""What the inference runs with: frozen, checked parameter objects, one per piece.

``SearchParams`` (``dejaview.inference.search.MapSearch``: the most probable past),
``SamplerParams`` (``dejaview.inference.sampling.Sampler``: the posterior's samples) and
``LocalParams`` (``dejaview.inference.local.fit_locally``: the seed's local optimisers with
restarts). Their defaults are the tool's; a researcher changes one with
``dataclasses.replace(SearchParams(), budget=20000)`` and passes it to the object that runs. Each
is checked when it is made: a value out of range is a one-line ``InferenceError`` naming it.
Beside them: ``ModelParams`` (physics variants), ``ReportParams`` (what a solve reports),
``StartAreaParams`` (the start area's check) and ``SizingParams`` (the memory a solve is sized with).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from dejaview.errors import InferenceError
from dejaview.scene.model import OPTIMIZERS

LOCAL_OPTIMIZERS = tuple(o for o in OPTIMIZERS if o != "auto")
"""The local optimisers (``auto`` is ``dejaview.inference.search.MapSearch``)."""


def check_params(params, *, counts=(), naturals=(), nonnegative=(), positive=(), fractions=(),
                 choices=None) -> None:
    """Raise ``InferenceError`` naming the first field of ``params`` out of its range.

    Args:
        counts: integer fields at least 1; naturals: integers at least 0; nonnegative: numbers >= 0 (None allowed);
            positive: numbers > 0; fractions: numbers in [0, 1]; choices: {field: allowed values}.
    """
    name = type(params).__name__
    for f in fields(params):
        v = getattr(params, f.name)
        if f.name in counts and not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
            raise InferenceError(f"{name}.{f.name} must be a positive integer, got {v!r}")
        if f.name in naturals and not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
            raise InferenceError(f"{name}.{f.name} must be a non-negative integer, got {v!r}")
        if f.name in nonnegative and v is not None and not (
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
            raise InferenceError(f"{name}.{f.name} must be a non-negative number, got {v!r}")
        if f.name in positive and not (isinstance(v, (int, float)) and not isinstance(v, bool)
                                       and math.isfinite(v) and v > 0):
            raise InferenceError(f"{name}.{f.name} must be a positive number, got {v!r}")
        if f.name in fractions and not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1):
            raise InferenceError(f"{name}.{f.name} must be a fraction in [0, 1], got {v!r}")
        if choices and f.name in choices and v not in choices[f.name]:
            raise InferenceError(f"{name}.{f.name} must be one of {', '.join(map(str, choices[f.name]))}, "
                                 f"got {v!r}")


@dataclass(frozen=True)
class SearchParams:
    """How the search for the most probable past runs (``MapSearch``); frozen, checked on creation.

    Attributes:
        iterations: most global iterations (a screening or a CMA-ES generation each; the LM
            iterations of a refinement are bounded by their own count).
        seed: seeds the prior draws and CMA-ES.
        budget: most rollouts per solve (a Jacobian counts ``jacobian_cost``): more than the searches
            of the bundled scenes need (docs/benchmarks.md, the recovery suite's table); a search
            that has not explained the observations within their noise goes on to it.
        tolerance: end once the best candidate's scene loss (metres) is at or below this (None: no).
        candidates: CMA-ES instances run side by side, each in its own basin, and candidates
            refined by LM.
        sigma0: initial CMA-ES step size in scaled parameters (5 cm, 0.25 rad, 0.5 m/s, 2.5 rad/s).
        seed_spacing: least distance between the screened starts of two instances (scaled).
        polish_every: generations between LM refinements of the instances' best points.
        lm_iterations: most LM iterations of one refinement.
        lm_final_iterations: most LM iterations of the final refinement of the best candidates
            (it stops once converged).
        stall_generations: an instance whose best cost fell by less than ``stall_ratio`` over this
            many generations stops.
        stall_ratio: relative gain that counts as progress.
        chi2_explained: observation chi-square per observed residual at or below which the end
            counts as explained and the search stops (a mean misfit of a tenth of the noise's
            standard deviation: a flat prior's maximum explains the end exactly).
        max_population_factor: a fresh instance doubles the population of the one it replaces
            (IPOP), up to this factor.
        global_patience: generations without a gain of ``stall_ratio`` in the best cost after which
            the search stops (where a prior keeps the maximum's misfit above ``chi2_explained``),
            once the best explains the observations within their noise; until then it goes on.
        noise_quantile: quantile of the chi-square law (a degree per observed residual) up to which
            a misfit is the observations' noise.
        jacobian_cost: budget units of one candidate's residual Jacobian (~3 rollouts).
        stage_share: share of the budget and iterations each earlier stage of a tracked source's
            search may spend (``MapSearch.run``).
        last_share: the least share of the iterations and budget the last stage of a tracked
            source's search (over every sighting) keeps, whatever the earlier stages spent: a box
            tracked at six moments had given its five earlier stages a quarter each and its last
            one iteration (cost 220 where its truth's is 25).
        sample_gain: a posterior sample, refined, replaces the search's answer where its negative
            log posterior is lower by at least this (nats; ``solve.refine_from_samples``): closer
            than that the two are alike in probability (the flagship demo's flat answer 0.22, a
            sample's 0.13, its end 9.8 mm off where the search's is 5.0 mm).
    """

    iterations: int = 200
    seed: int = 0
    budget: int = 40000
    tolerance: float | None = None
    candidates: int = 4
    sigma0: float = 0.5
    seed_spacing: float = 1.0
    polish_every: int = 10
    lm_iterations: int = 8
    lm_final_iterations: int = 30
    stall_generations: int = 15
    stall_ratio: float = 1e-3
    chi2_explained: float = 0.01
    max_population_factor: int = 4
    global_patience: int = 40
    noise_quantile: float = 0.999
    jacobian_cost: int = 3
    stage_share: float = 0.25
    last_share: float = 0.5
    sample_gain: float = 1.0

    def __post_init__(self):
        check_params(self, counts=("iterations", "budget", "candidates", "polish_every", "stall_generations",
                                   "max_population_factor", "global_patience", "jacobian_cost"),
                     naturals=("lm_iterations", "lm_final_iterations"),
                     nonnegative=("seed", "tolerance", "chi2_explained", "sample_gain"),
                     positive=("sigma0", "seed_spacing"),
                     fractions=("stall_ratio", "noise_quantile", "stage_share", "last_share"))


@dataclass(frozen=True)
class SamplerParams:
    """How the posterior sampler runs (``dejaview.inference.sampling.Sampler``); frozen, checked.

    Attributes:
        seed: seeds the sampler (each run ``seed + 7919 i``).
        ess_fraction: effective sample size kept by each tempering step, a fraction of the particles.
        rw_moves: random-walk Metropolis moves per tempering step (after one independence move),
            every other one a differential-evolution step.
        final_moves: moves run at beta = 1 before the samples are returned.
        target_acceptance: random-walk acceptance rate the step scale adapts towards.
        max_stages: most tempering steps (a safety net; each needs a 1e-6 increase of beta).
        prior_share: weight of the prior itself in the reference mixture (defensive importance
            sampling): branches the search did not find are reached by tempering from the prior.
        distinct_fraction: a tempering step's moves go on until this fraction of the particles are
            distinct ...
        max_moves: ... or this many moves have run.
        population_moves: the first random-walk move of each step is a population move
            (docs/benchmarks.md, "Posterior: calibration and speed").
        runs: independent runs that share the particles and the samples equally: their agreement
            (``posterior_report.rhat``) says whether the samples can be trusted.
        min_run_size: fewer particles than ``runs`` times this: one run.
        particles: fewer samples than this are a random subset of twice as many particles, up to
            this many (all runs together; docs/benchmarks.md, "More particles").
        symmetry_moves: each tempering step moves the particles along the scene's symmetry
            (``dejaview.inference.symmetry``), where it has one.
        difference_moves: every other random-walk move is a differential-evolution step.
        reference_df: degrees of freedom of the reference mixture's Student-t components
            (``reference.laplace_mixture``; heavy tails: the Laplace approximation of a contact
            landscape is only local).
        scale_inflation: the reference components' scale over the Laplace standard deviation.
        mode_merge: modes closer than this Mahalanobis distance (under the better one's Laplace
            covariance) are one component.
        orbit_draws: motions drawn per orbit in the symmetry moves' importance sampling
            (``symmetry.orbit_walk``; each costs no rollout; docs/benchmarks.md, "Symmetry moves").
        orbit_width: the symmetry moves' proposal spread over the tempered observation noise.
        sightings: a tracked source (several observed moments) is sampled sighting after sighting:
            the bridge tempers in the observations up to each moment in turn (``search.stages``).
        kde_rows: the population move's kernel density estimate is computed for this many
            particles at a time (a (rows, guides) matrix instead of (particles, guides): the same
            numbers in less memory; ``dejaview.inference.sizing.kde_rows``); 0: all at once.
    """

    seed: int = 0
    ess_fraction: float = 0.7
    rw_moves: int = 4
    final_moves: int = 8
    target_acceptance: float = 0.3
    max_stages: int = 200
    prior_share: float = 0.3
    distinct_fraction: float = 0.9
    max_moves: int = 7
    population_moves: bool = True
    runs: int = 2
    min_run_size: int = 20
    particles: int = 600
    symmetry_moves: bool = True
    difference_moves: bool = True
    reference_df: float = 5.0
    scale_inflation: float = 1.5
    mode_merge: float = 3.0
    orbit_draws: int = 128
    orbit_width: float = 1.5
    kde_rows: int = 0
    sightings: bool = True

    def __post_init__(self):
        check_params(self, counts=("max_stages", "max_moves", "runs", "min_run_size", "particles", "orbit_draws"),
                     positive=("reference_df", "scale_inflation", "mode_merge", "orbit_width"),
                     naturals=("seed", "rw_moves", "final_moves", "kde_rows"),
                     fractions=("ess_fraction", "target_acceptance", "prior_share", "distinct_fraction"),
                     choices={"population_moves": (True, False), "symmetry_moves": (True, False),
                              "difference_moves": (True, False)})
        if not 0.0 < self.ess_fraction < 1.0:
            raise InferenceError(f"SamplerParams.ess_fraction must lie strictly between 0 and 1, "
                                 f"got {self.ess_fraction!r}")


@dataclass(frozen=True)
class LocalParams:
    """How the local pipeline runs (``fit_locally``); frozen, checked.

    Attributes:
        optimizer: ``gd|adam|lbfgs|bfgs``.
        iterations, seed: budget and seed.
        tolerance: end once the loss (metres) is at or below this (None: no).
        gradient: ``forward|reverse`` (None: ``default_gradient``); lr: step size (None: the
            optimiser's default).
        multistart: K guesses optimised as one batch.
        screen: random guesses ranked by loss first (0: none); screen_rounds: 1 + cross-entropy
            refinements of the screening.
        screen_near: fraction of the first screening round drawn near the scene's own guess. 0:
            near draws rank high together, so the best start and the restarts after it all tell
            one story, and the search loses the diversity of the prior.
        screen_sigma: standard deviation of those draws in scaled parameters (0.1 m / 0.5 rad /
            1 m/s / 5 rad/s; positions in the start area's logit coordinates).
        screen_batch: candidates per batch while screening (bounds memory; batching amortises the
            per-op overhead).
        epsilon, patience: a start that has not improved for ``patience`` iterations hops to a
            fresh guess with probability ``epsilon`` (``optimize``).
        stall_ratio: an iteration improves a candidate when its best objective falls by more than
            this fraction.
        line_search_evals: most objective evaluations one L-BFGS/BFGS line search may spend in one
            iteration.
        hop_scale: range of a hop's standard deviation (scaled parameters, drawn log-uniformly per
            hop): from 1 mm / 0.6 degrees / 2 cm/s fine-tuning to 5 cm / 14 degrees / 0.5 m/s
            jumps (default scales).
    """

    optimizer: str = "lbfgs"
    iterations: int = 100
    seed: int = 0
    tolerance: float | None = None
    gradient: str | None = None
    lr: float | None = None
    multistart: int = 1
    screen: int = 0
    screen_rounds: int = 1
    screen_near: float = 0.0
    screen_sigma: float = 1.0
    screen_batch: int = 64
    epsilon: float = 0.0
    patience: int = 25
    stall_ratio: float = 1e-3
    line_search_evals: int = 10
    hop_scale: tuple[float, float] = (0.02, 0.5)

    @property
    def step_size(self) -> float:
        """``lr``, else the optimiser's default on the 0.5 * loss^2 objective in scaled parameters."""
        return self.lr if self.lr is not None else {"gd": 1.0, "adam": 0.05, "lbfgs": 1.0, "bfgs": 1.0}[self.optimizer]

    def __post_init__(self):
        if not (isinstance(self.hop_scale, tuple) and len(self.hop_scale) == 2
                and 0 < self.hop_scale[0] <= self.hop_scale[1] < math.inf):
            raise InferenceError(f"LocalParams.hop_scale must be two increasing positive numbers, "
                                 f"got {self.hop_scale!r}")
        check_params(self, counts=("iterations", "multistart", "screen_rounds", "screen_batch", "patience",
                                   "line_search_evals"),
                     naturals=("seed", "screen"), nonnegative=("tolerance", "lr"), positive=("screen_sigma",),
                     fractions=("screen_near", "epsilon", "stall_ratio"),
                     choices={"optimizer": LOCAL_OPTIMIZERS, "gradient": (None, "forward", "reverse")})


@dataclass(frozen=True)
class ModelParams:
    """How ``<model-uncertainty>``'s physics variants are drawn and judged
    (``dejaview.inference.model_uncertainty``).

    Attributes:
        stiffness_sd: relative standard deviation of the contact stiffness (k = m omega_0^2) when
            any model uncertainty is asked for: the penalty stiffness is a numerical choice, not a
            measured property (MuJoCo's contact, a real table), so the answer should not hinge on it.
        variants: physics variants the likelihood averages over (4: the 2^(3-1) design).
        heldout_variants: variants, drawn apart from the design's, that rank the refined modes
            (``rank_on_heldout``): an estimate of each mode's mean cost over the physics'
            uncertainty whose noise decides between close modes (docs/physics-fidelity.md,
            "64 held-out variants"); 64 rollouts of a few modes cost about a second.
        heldout_seed: added to the solve's seed for the held-out draws (another stream).
        unexplained_p: a refined mode whose held-out variants' mean end is off the observation by
            more than the ``1 - unexplained_p`` quantile of its chi-square (22.5 for a pose's 6
            residuals) does not explain the end (``explains_end``; docs/physics-fidelity.md,
            "When no refined mode explains the end").
        min_factor: a variant's friction or stiffness is at least this fraction of the scene's.
    """

    stiffness_sd: float = 0.25
    variants: int = 4
    heldout_variants: int = 64
    heldout_seed: int = 7919
    unexplained_p: float = 1e-3
    min_factor: float = 0.05

    def __post_init__(self):
        check_params(self, counts=("variants", "heldout_variants"), naturals=("heldout_seed",),
                     positive=("stiffness_sd",), fractions=("unexplained_p", "min_factor"))


@dataclass(frozen=True)
class ReportParams:
    """What a solve reports of its answer and its samples (``posterior_report``, ``rest``).

    Attributes:
        intervals: central credible intervals reported for every free parameter.
        min_mode_mass: modes holding less posterior mass are left out of the summary.
        rhat_limit: the runs agree when every parameter's rank-normalised R-hat is at most this
            (Gelman and Rubin's threshold; docs/inference.md, "The posterior", has how often 1.05
            and 1.1 flag the calibration bench's truths, and how those truths' intervals fare).
        paths: samples whose trajectories ``posterior_paths.csv`` holds (drawn faintly by the viewer).
        path_records: about how many records each of those trajectories keeps.
        rest_level: mean speeds (and spins) above this many ``rest_speed`` (``rest_spin``) count as
            moving (``rest.duration_warnings``).
        extend_factor: how far past the start a rest is looked for, in scene durations.
        max_checked: most posterior samples (the heaviest distinct ones) checked for rest.
    """

    intervals: tuple[float, ...] = (0.5, 0.9)
    min_mode_mass: float = 1e-3
    rhat_limit: float = 1.1
    paths: int = 8
    path_records: int = 60
    rest_level: float = 2.0
    extend_factor: float = 4.0
    max_checked: int = 64

    def __post_init__(self):
        check_params(self, counts=("paths", "path_records", "max_checked"),
                     positive=("rhat_limit", "rest_level", "extend_factor"), fractions=("min_mode_mass",))
        if not all(isinstance(x, float) and 0 < x < 1 for x in self.intervals):
            raise InferenceError(f"ReportParams.intervals must be levels strictly between 0 and 1, "
                                 f"got {self.intervals!r}")


@dataclass(frozen=True)
class StartAreaParams:
    """How hard ``start_area.check_start_area`` looks for a start the area can hold.

    Attributes:
        draws: random starts tried after the scene's own and the box's centre.
        orientations: random orientations tried at each cell's centre (besides the ``<pose>`` one).
        budget: most placements tried (about 0.2 s for primitives, a few seconds for a concave
            mesh; only an area with no free start found runs that far).
        batch: cells evaluated together (one collision query each).
        recheck: placements with the least depth bounds whose full depth is measured for the message.
        named: objects the message names (the rest are counted).
    """

    draws: int = 256
    orientations: int = 7
    budget: int = 4096
    batch: int = 32
    recheck: int = 8
    named: int = 3

    def __post_init__(self):
        check_params(self, counts=("draws", "orientations", "budget", "batch", "recheck", "named"))


@dataclass(frozen=True)
class IdentifyParams:
    """Settings of ``identify`` (``dejaview.inference.identify``).

    Attributes:
        friction, restitution, stiffness: relative standard deviations of the physics prior for
            scenes without ``<physics-prior>`` (log-normal around the scenes' values).
        samples: importance samples of the joint posterior (0: the Laplace intervals alone).
        seed: the searches' and the samples' seed.
        search: each scene's ``MapSearch`` settings.
        lm_iterations: joint Levenberg-Marquardt iterations at most.
        rounds: most rounds of searching the starts again under the joint physics.
        min_ess_share: importance samples are kept where their effective size is at least this
            share of their count (else the intervals are the Laplace approximation's).
        grid: nodes of the physics' marginal posterior grid in all (``physics_marginal``; odd per
            axis, at most ``grid_axis`` per axis); 0: the intervals are the joint Laplace
            approximation's (or the importance samples').
        grid_sds: the grid's first half-width per axis, in the joint Laplace standard deviations ...
        grid_min_width, grid_max_width: ... at least and at most these (z, prior standard deviations).
        grid_widen: an axis whose edge holds mass (within ``grid_edge_nats`` of the largest node)
            is widened by this factor, up to ``grid_passes`` grids in all.
        grid_iterations: Levenberg-Marquardt iterations of each scene's start at each node.
        scan: before the rounds, the physics scanned over the prior on this many nodes in all
            (``physics_marginal.scan``; 0: no scan) ...
        scan_width: ... over +- this many prior standard deviations; the ``scan_keep`` nodes of
            least joint cost refined jointly.
    """

    friction: float = 0.5
    restitution: float = 0.5
    stiffness: float = 0.0
    samples: int = 0
    seed: int = 0
    search: SearchParams = field(default_factory=SearchParams)
    lm_iterations: int = 60
    rounds: int = 2
    min_ess_share: float = 0.02
    grid: int = 121
    grid_axis: int = 15
    grid_sds: float = 4.0
    grid_min_width: float = 0.5
    grid_max_width: float = 4.0
    grid_widen: float = 2.5
    grid_edge_nats: float = 6.0
    grid_passes: int = 3
    grid_iterations: int = 12
    scan: int = 81
    scan_width: float = 2.5
    scan_keep: int = 3

    def __post_init__(self):
        check_params(self, nonnegative=("friction", "restitution", "stiffness"),
                     naturals=("samples", "seed", "rounds", "grid", "scan"),
                     counts=("lm_iterations", "grid_axis", "grid_passes", "grid_iterations", "scan_keep"),
                     fractions=("min_ess_share",), positive=("grid_sds", "grid_min_width", "grid_max_width", "scan_width",
                                                            "grid_widen", "grid_edge_nats"))


    named: int = 3

    def __post_init__(self):
        check_params(self, counts=("draws", "orientations", "budget", "batch", "recheck", "named"))


@dataclass(frozen=True)
class SizingParams:
    """The memory a solve is sized with before it runs (``dejaview.inference.sizing``): peaks
    measured on the bundled scenes and rounded up (docs/benchmarks.md, "Sized before run", has the
    measurements and the commands); frozen, checked.

    Attributes:
        search_bytes: memory the default search holds at its peak beyond the built problem.
        rollout_copies: records' worth of memory a candidate of a batch of rollouts holds at the
            batch's peak.
        kde_copies: (M, M) float64 matrices the sampler's population move holds at its peak for M
            guides (the kernels, cdist's distances and their square).
        particle_bytes: the rest a particle holds (its state, the moves' proposals,
            ``torch.unique``'s copies).
        min_kde_rows: fewest particles a chunk of the kernel density estimate holds: below it, the
            request is refused.
        pair_copies: copies of the training set (its starts and observation vectors, float64) an
            amortised training holds at its peak (the chunks and their concatenation; the flow
            coordinates, standardised, beside them).
        flow_copies: copies of the flow's parameters its fit holds (the parameters, their gradients,
            Adam's two moments, the best epoch's).
        activation_copies: copies of a transform's activations (its hidden layers and the spline
            parameters it outputs, float64) the flow's fit holds per pair of a batch and transform
            (the forward pass and its gradients).
        validation_copies: copies of one transform's activations per validation pair (evaluated
            without gradients, a transform at a time).
        fit_bytes: the rest of a fit's peak (zuko, autograd and the optimiser's first use).
        min_rollout_batch: fewest starts a batch of a training's rollouts holds: below it, the
            request is refused.
    """

    search_bytes: int = 128 * 2 ** 20
    rollout_copies: int = 3
    kde_copies: int = 5
    particle_bytes: int = 16384
    min_kde_rows: int = 64
    pair_copies: int = 4
    flow_copies: int = 5
    activation_copies: int = 4
    validation_copies: int = 2
    fit_bytes: int = 144 * 2 ** 20
    min_rollout_batch: int = 16

    def __post_init__(self):
        check_params(self, counts=("search_bytes", "rollout_copies", "kde_copies", "particle_bytes",
                                   "min_kde_rows", "pair_copies", "flow_copies", "activation_copies", "validation_copies",
                                   "fit_bytes",
                                   "min_rollout_batch"))


@dataclass(frozen=True)
class TrainParams:
    """How an amortised posterior is trained (``dejaview.inference.amortised.train``); frozen, checked.

    Attributes:
        simulations: training pairs (feasible starts drawn from the prior, each simulated once).
        seed: seeds the draws (chunk i draws from ``seed`` and i alone: the same set whichever
            workers or Ray actors simulate it) and the fit.
        chunk: starts drawn per chunk of simulation work (one batch of the native engine).
        workers: processes simulating chunks at once (1: this process, its engine's threads).
        ray: None, ``local`` or a Ray cluster address (``dejaview.parallel``).
        transforms, hidden, bins: the flow's shape (``amortised.model.FlowShape``).
        batch: training pairs per gradient step; lr: Adam's step (cosine-annealed to 0).
        epochs: most passes over the training pairs; patience: epochs without a better validation
            loss before the fit stops (the best epoch's weights are kept).
        validation: share of the pairs held out of the fit to choose the epoch.
        max_fit_seconds: the fit stops after this long (its best epoch kept).
        memory_limit: bytes the training may take (``dejaview.memory``; None: the machine's):
            sized before any simulation (``amortised.sizing.check_train_memory``), its rollouts simulated a
            smaller batch at a time where a whole chunk's do not fit (the same training set).
    """

    simulations: int = 20000
    seed: int = 0
    chunk: int = 512
    workers: int = 1
    ray: str | None = None
    transforms: int = 4
    hidden: tuple[int, ...] = (128, 128)
    bins: int = 8
    batch: int = 256
    lr: float = 1e-3
    epochs: int = 200
    patience: int = 15
    validation: float = 0.1
    max_fit_seconds: float = 150.0
    memory_limit: int | None = None

    def __post_init__(self):
        check_params(self, counts=("simulations", "chunk", "workers", "transforms", "bins", "batch", "epochs",
                                   "patience"),
                     naturals=("seed",), positive=("lr", "max_fit_seconds"), fractions=("validation",))
        if not self.hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in self.hidden):
            raise InferenceError(f"TrainParams.hidden must be positive layer widths, got {self.hidden!r}")
        if not 0.0 < self.validation < 0.5:
            raise InferenceError(f"TrainParams.validation must lie in (0, 0.5), got {self.validation!r}")


@dataclass(frozen=True)
class AmortisedParams:
    """How an answer is drawn from an amortised posterior (``dejaview.inference.amortised.answer``).

    Attributes:
        draws: draws from the flow per requested sample (each simulated once for its exact
            likelihood), at least ``min_draws`` in all.
        max_k_hat: Pareto k-hat of the importance weights above which the flow is taken not to fit
            the observation (Vehtari et al. 2024: above 0.7 the estimate is unreliable), and the
            answer falls back to the sampler with the flow in its proposal.
        refine: the best weighted draws refined by Levenberg-Marquardt for the most probable start.
        flow_share: in the fallback, the flow's share of the sampler's reference mixture.
        live_draws: draws of a live answer (``live``): from the flow alone, no rollout.
    """

    draws: int = 4
    min_draws: int = 1000
    max_k_hat: float = 0.7
    refine: int = 4
    flow_share: float = 0.5
    live_draws: int = 1000

    def __post_init__(self):
        check_params(self, counts=("draws", "min_draws", "refine", "live_draws"), positive=("max_k_hat",),
                     fractions=("flow_share",))
