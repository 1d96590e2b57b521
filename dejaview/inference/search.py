"""The default search for the most probable past: CMA-ES over the prior, then Levenberg-Marquardt.

The objective is the negative log posterior ``0.5 |R(x)|^2`` of
``dejaview.inference.posterior``: a small nonlinear least-squares problem (6
observation residuals plus the prior's, 1 to 13 unknowns) whose landscape is
full of contact kinks and basins (the mug lands on its side or upright, the
handle here or there). So the search has a global and a local stage:

1. **screen**: ``screen_size(P)`` starts drawn from the prior (and the scene's
   own guess) are simulated as one batch without gradients; infeasible starts
   (interpenetrating, ``Posterior.feasible``) cost nothing and count as inf.
2. **global**: ``candidates`` CMA-ES instances (the ``cma`` package: the
   reference implementation by N. Hansen, with its step-size and covariance
   adaptation), each started at one of the best screened starts that lie at
   least ``seed_spacing`` apart (scaled parameters), so they explore distinct
   basins. Their populations are evaluated together as one native batch, one
   generation per iteration.
3. **local**: every ``polish_every`` generations, and when an instance stops,
   the best point of each instance is refined by Levenberg-Marquardt on the
   exact residual Jacobian (``Posterior.jacobian``), all candidates as one
   batch, each with its own damping. Near a solution LM converges in a handful
   of iterations where L-BFGS on the summed squares needs dozens (quadratic
   convergence on a small-residual problem).

The search ends when the best candidate explains the observation (its
observation chi-square is at most ``chi2_explained`` per observed residual)
after a refinement and the prior is flat, when the best cost has not improved for ``global_patience``
generations, when every instance has stopped and no fresh start is left to
try, or when the budget (``iterations``: screenings + generations;
``budget``: rollouts, a Jacobian counting ``jacobian_cost``) runs out. Stopped
instances are replaced by fresh ones (from the next distinct screened starts,
with twice the population: IPOP) while the budget lasts.

Measured against the seed's screening + L-BFGS + restarts: see ``dejaview bench search``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from dejaview.inference.optimize import OptimizationResult, Progress
from dejaview.inference.params import SearchParams

def screen_size(num_params: int) -> int:
    """Starts screened from the prior: 64 for a 2-parameter problem, 256 for 12."""
    return int(min(256, max(64, 24 * num_params)))


def population(num_params: int) -> int:
    """CMA-ES population per instance: twice Hansen's default ``4 + 3 ln P`` (contact landscapes
    are rugged; a larger population smooths the ranking)."""
    return 2 * (4 + int(3 * math.log(max(num_params, 1))))


@dataclass
class Mode:
    """A refined candidate: parameters (P,), negative log posterior, observation chi-square, loss;
    under model uncertainty also its negative log posterior under the held-out physics variants
    that rank the modes (``model_uncertainty.rank_on_heldout``) and the observation chi-square of
    their mean end, else None."""

    x: torch.Tensor
    cost: float
    chi2: float
    loss: float
    heldout: float | None = None
    heldout_mean_chi2: float | None = None


@dataclass
class SearchResult(OptimizationResult):
    """``OptimizationResult`` plus what the search found.

    Attributes:
        cost: negative log posterior of ``x`` (``loss`` is the scene's loss there, metres).
        chi2: its observation chi-square.
        modes: distinct refined candidates, best first.
        rollouts, jacobians: evaluations spent.
    """

    cost: float = math.inf
    chi2: float = math.inf
    modes: list = field(default_factory=list)
    rollouts: int = 0
    jacobians: int = 0


class _Search:
    """State of one search stage (``MapSearch``); its methods are the named steps."""

    def __init__(self, post, params: SearchParams, callback, should_stop, seeds=None, near=None):
        self.post = post
        self.p = params
        self.seeds = seeds
        self.near = near
        self.lay = post.layout
        self.P = self.lay.size
        self.iterations = params.iterations
        self.seed = int(params.seed)
        self.gen = torch.Generator().manual_seed(self.seed)
        self.callback, self.should_stop = callback, should_stop
        self.tolerance = params.tolerance
        self.budget = params.budget
        self.t0 = time.perf_counter()
        self.last = self.t0
        self.history: list[Progress] = []
        self.best = Mode(self.lay.encode().to(torch.float64)[0], math.inf, math.inf, math.inf)
        self.modes: list[Mode] = []
        self.pool: list[torch.Tensor] = []
        self.stopped = False
        self.done = False
        self.n_obs = None
        self.generations = 0
        self.global_iterations = 0
        self.improved_at = 0

    # -------------------------------------------------------------- bookkeeping
    def spent(self) -> int:
        return self.post.rollouts + self.p.jacobian_cost * self.post.jacobians

    def out_of_budget(self) -> bool:
        """The budget is spent: ``iterations`` global iterations (screenings and CMA-ES generations;
        the LM iterations of each refinement are bounded by their own count) or ``budget`` rollouts."""
        return self.global_iterations >= self.iterations or self.spent() >= self.budget

    def consider(self, x: torch.Tensor, cost: torch.Tensor, chi2: torch.Tensor, loss: torch.Tensor) -> float:
        """Keep the best of a batch; returns the batch's best cost."""
        i = int(torch.argmin(cost))
        if float(cost[i]) < self.best.cost * (1 - self.p.stall_ratio):
            self.improved_at = self.generations
        if float(cost[i]) < self.best.cost:
            self.best = Mode(x[i].detach().clone(), float(cost[i]), float(chi2[i]), float(loss[i]))
        return float(cost[i])

    def tick(self, value: float, restarted: bool = False, phase: str = "search") -> None:
        """One iteration: record progress, call back, poll for a stop."""
        now = time.perf_counter()
        p = Progress(iteration=len(self.history), loss=value, best_loss=self.best.cost,
                     duration_s=now - self.last, elapsed_s=now - self.t0, restarted=restarted,
                     evaluations=self.spent(), phase=phase)
        self.last = now
        self.history.append(p)
        self.global_iterations += phase != "refine"
        if self.callback is not None:
            self.callback(p)
        if self.should_stop is not None and self.should_stop():
            self.stopped = True
        if self.tolerance is not None and self.best.loss <= self.tolerance:
            self.done = True

    def explained(self, mode: Mode) -> bool:
        """A flat prior's maximum explains the end exactly: a candidate that comes within
        ``chi2_explained`` ends the search. Under an informative prior the first past that explains
        the end need not be the most probable one, so the search goes on (``global_patience``)."""
        return self.post.prior_is_flat and mode.chi2 <= self.p.chi2_explained * self.n_obs

    def within_noise(self) -> bool:
        """Whether the best candidate explains the observations as well as their noise allows:
        its observation chi-square at most the ``noise_quantile`` quantile of the chi-square law
        with one degree per observed residual. Until then patience does not end the search."""
        from scipy.stats import chi2

        return self.best.chi2 <= float(chi2.ppf(self.p.noise_quantile, self.n_obs))

    def rescreen(self) -> None:
        """Fresh draws from the prior for the pool, where it has run dry and the observations are
        not explained yet."""
        x = self.post.sample(screen_size(self.P), self.gen)
        cost, chi2, loss = self.post.cost(x)
        self.consider(x, cost, chi2, loss)
        order = torch.argsort(cost, stable=True)
        self.pool += [x[i] for i in order.tolist() if math.isfinite(float(cost[i]))]
        self.tick(float(cost.min()))

    def finished(self) -> bool:
        return self.stopped or self.done or self.out_of_budget()

    # -------------------------------------------------------------- stages
    def screen(self) -> None:
        """Rank the scene's guess and draws from the prior; fill the pool of instance seeds.

        The scene's own guess (its ``<pose>`` and ``<velocity>``: what the user or robot assumes)
        goes first in the pool whatever its cost, when feasible: one instance always starts there.
        Given ``near`` draws (an earlier stage's, ``laplace_draws``), they and the given seeds go
        first, best first, then the guess.
        """
        guess = self.lay.encode().to(torch.float64)
        given = (self.seeds.to(torch.float64) if self.seeds is not None else guess[:0])
        near = (self.near.to(torch.float64) if self.near is not None else guess[:0])
        k = 1 + given.shape[0] + near.shape[0]
        x = torch.cat([guess, given, near, self.post.sample(screen_size(self.P), self.gen)], 0)
        cost, chi2, loss = self.post.cost(x)
        self.consider(x, cost, chi2, loss)
        order = torch.argsort(cost[k:], stable=True) + k
        first = [i for i in range(k) if math.isfinite(float(cost[i]))]  # the given seeds, then the guess
        if near.shape[0]:
            first = sorted((i for i in first if i > 0), key=lambda i: float(cost[i])) + [i for i in first if i == 0]
        first = first[1:] + first[:1] if first and first[0] == 0 else first
        self.pool = [x[i] for i in first] + [x[i] for i in order.tolist() if math.isfinite(float(cost[i]))]
        self.tick(float(cost.min()))

    def take_seeds(self, k: int, avoid: list[torch.Tensor]) -> list[torch.Tensor]:
        """Up to k pool entries, best first, ``seed_spacing`` apart from each other and ``avoid``."""
        out, rest = [], []
        for x in self.pool:
            if len(out) < k and all(float((x - y).norm()) >= self.p.seed_spacing for y in out + avoid):
                out.append(x)
            else:
                rest.append(x)
        self.pool = rest
        return out

    def new_instance(self, x0: torch.Tensor, popsize: int):
        import cma

        opts = {"popsize": popsize, "seed": self.seed * 7919 + len(self.history) + 1, "verbose": -9,
                "tolfun": 1e-12, "tolx": 1e-9}
        es = cma.CMAEvolutionStrategy(x0.numpy(), self.p.sigma0, opts)
        es.dejaview_best = (math.inf, 0)  # (best cost, generation it was reached)
        return es

    def generation(self, instances: list) -> None:
        """One CMA-ES generation of every instance, evaluated as one batch."""
        asks = [es.ask() for es in instances]
        x = torch.as_tensor(np.concatenate(asks), dtype=torch.float64)
        cost, chi2, loss = self.post.cost(x)
        self.generations += 1
        value = self.consider(x, cost, chi2, loss)
        ranked = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, 1e300)).numpy()
        start = 0
        for es, a in zip(instances, asks):
            f = ranked[start:start + len(a)]
            start += len(a)
            es.tell(a, f.tolist())
            if f.min() < es.dejaview_best[0] * (1 - self.p.stall_ratio):
                es.dejaview_best = (float(f.min()), es.countiter)
        self.tick(value)

    def stalled(self, es) -> bool:
        return bool(es.stop()) or es.countiter - es.dejaview_best[1] >= self.p.stall_generations

    def refine(self, x: torch.Tensor, iterations: int | None = None) -> list[Mode]:
        """Levenberg-Marquardt from each row of x (K, P), as one batch; the refined modes."""
        post = self.post
        iterations = self.p.lm_iterations if iterations is None else iterations
        cost, chi2, loss = post.cost(x)
        ok = torch.isfinite(cost)
        if not bool(ok.any()):
            return []
        x, cost, chi2, loss = x[ok], cost[ok], chi2[ok], loss[ok]
        k = x.shape[0]
        lam = torch.full((k,), 1e-2, dtype=x.dtype)
        active = torch.ones(k, dtype=torch.bool)
        r, J = post.jacobian(x)
        for it in range(iterations):
            if self.stopped or self.out_of_budget() or not bool(active.any()):
                break
            trial = x + lm_step(r, J, lam)
            c_t, chi_t, l_t = post.cost(trial)
            better = active & (c_t < cost)
            rel = (cost - c_t) / cost.clamp_min(1e-300)
            lam = torch.where(better, (lam / 3).clamp_min(1e-9), lam * 4)
            x = torch.where(better[:, None], trial, x)
            cost = torch.where(better, c_t, cost)
            chi2 = torch.where(better, chi_t, chi2)
            loss = torch.where(better, l_t, loss)
            # converged: no relative gain left, or the damping says there is no descent nearby
            active = active & ~((better & ((rel < 1e-10) | (cost < 1e-12))) | (lam > 1e8))
            value = self.consider(x, cost, chi2, loss)
            self.tick(value, phase="refine")
            if it + 1 < iterations and not self.out_of_budget():
                idx = (better & active).nonzero().flatten()
                if idx.numel():
                    r_new, J_new = post.jacobian(x[idx])
                    r, J = r.clone(), J.clone()
                    r[idx], J[idx] = r_new, J_new
        return [Mode(x[i].clone(), float(cost[i]), float(chi2[i]), float(loss[i])) for i in range(k)]

    def add_modes(self, found: list[Mode]) -> None:
        """Keep refined candidates; one within ``0.1 * seed_spacing`` of a kept one replaces it
        when better."""
        for m in found:
            near = [i for i, o in enumerate(self.modes) if float((m.x - o.x).norm()) < self.p.seed_spacing * 0.1]
            if not near:
                self.modes.append(m)
            elif m.cost < self.modes[near[0]].cost:
                self.modes[near[0]] = m
        self.modes.sort(key=lambda m: m.cost)

    def run(self) -> None:
        self.screen()
        self.n_obs = max(1, self.post.num_observed)
        if self.near is not None and self.near.shape[0] and self.pool and not self.finished():
            # an earlier stage's uncertainty screened (``laplace_draws``): its best refined at once,
            # the refined ones first in the pool
            k = 2 * self.p.candidates
            found = sorted(self.refine(torch.stack(self.pool[:k]), self.p.lm_final_iterations), key=lambda m: m.cost)
            self.add_modes(found)
            self.pool = [m.x for m in found] + self.pool[k:]
        popsize = population(self.P)
        instances = [self.new_instance(x, popsize) for x in self.take_seeds(self.p.candidates, [])]
        while instances and not self.finished():
            self.generation(instances)
            if self.generations - self.improved_at >= self.p.global_patience and self.within_noise():
                break
            ended = [es for es in instances if self.stalled(es)]
            polish = ended or instances[0].countiter % self.p.polish_every == 0
            if polish and not self.finished():
                pick = ended if ended else instances
                found = self.refine(torch.as_tensor(np.stack([es.result.xbest for es in pick]),
                                                    dtype=torch.float64))
                self.add_modes(found)
                if self.modes and self.explained(self.modes[0]) and self.modes[0].cost <= self.best.cost:
                    break
            if ended:
                instances = [es for es in instances if es not in ended]
                popsize = min(popsize * 2, self.p.max_population_factor * population(self.P))
                taken = [torch.as_tensor(es.result.xbest, dtype=torch.float64) for es in instances]
                fresh = self.take_seeds(len(ended), taken + [m.x for m in self.modes])
                if len(fresh) < len(ended) and not self.within_noise() and not self.finished():
                    self.rescreen()  # the pool ran dry before the observations were explained
                    fresh += self.take_seeds(len(ended) - len(fresh), taken + [m.x for m in self.modes] + fresh)
                instances += [self.new_instance(x, popsize) for x in fresh]
                if self.history:
                    self.history[-1].restarted = True
        # converge the best candidates fully (the best so far and the best refined modes: under
        # an informative prior a mode behind the best one may refine to a more probable past)
        if not self.stopped and math.isfinite(self.best.cost):
            starts = [self.best.x] + [m.x for m in self.modes[:self.p.candidates - 1]]
            self.add_modes(self.refine(torch.stack(starts), self.p.lm_final_iterations))


def levenberg_marquardt(x: torch.Tensor, cost_of, jacobian_of, iterations: int, *, tolerance: float,
                        jacobian_at_end: bool = False):
    """Levenberg-Marquardt from each row of x (K, P), as one batch, on a cost 0.5 |r|^2.

    Args:
        x: (K, P) the starts.
        cost_of: x (B, P) -> cost (B,) (inf: not finite; such rows do not move).
        jacobian_of: (x (B, P), rows (B,) their indices in x) -> residuals (B, M), Jacobian (B, M, P).
        iterations: most iterations.
        tolerance: a row stops when a step gains less than this share of its cost (or the damping
            passes 1e8).
        jacobian_at_end: the Jacobian is also recomputed for a row whose last step stopped it, so
            the returned one is at the returned x for every row that moved.
    Returns:
        (x (K, P), cost (K,), residuals (K, M), Jacobian (K, M, P)).
    """
    cost = cost_of(x)
    lam = torch.full((x.shape[0],), 1e-2, dtype=x.dtype)
    active = torch.isfinite(cost)
    r, J = jacobian_of(x, torch.arange(x.shape[0]))
    for _ in range(iterations):
        if not bool(active.any()):
            break
        trial = x + lm_step(r, J, lam)
        c_t = cost_of(trial)
        better = active & (c_t < cost)
        rel = (cost - c_t) / cost.clamp_min(1e-300)
        lam = torch.where(better, (lam / 3).clamp_min(1e-9), lam * 4)
        x = torch.where(better[:, None], trial, x)
        cost = torch.where(better, c_t, cost)
        active = active & ~((better & (rel < tolerance)) | (lam > 1e8))
        idx = (better if jacobian_at_end else better & active).nonzero().flatten()
        if idx.numel():
            r_new, J_new = jacobian_of(x[idx], idx)
            r, J = r.clone(), J.clone()
            r[idx], J[idx] = r_new, J_new
    return x, cost, r, J


def lm_step(r: torch.Tensor, J: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Levenberg-Marquardt steps (K, P) from residuals r (K, M), their Jacobians J (K, M, P) and
    damping lam (K,) on J^T J's diagonal (Marquardt's scaling); a non-finite entry is 0."""
    JT = J.transpose(1, 2)
    JTJ = JT @ J
    g = (JT @ r.unsqueeze(-1)).squeeze(-1)
    d = torch.diagonal(JTJ, dim1=1, dim2=2).clamp_min(1e-12)
    step = -_spd_solve(JTJ + torch.diag_embed(lam[:, None] * d), g)
    return torch.where(torch.isfinite(step), step, torch.zeros_like(step))


def _spd_solve(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """x (K, P) with A x = b for the damped normal matrices A (K, P, P) of Levenberg-Marquardt.

    By Cholesky: reproducible bit for bit (MKL's ``lstsq`` is not: the same inputs gave answers
    6e-17 apart from call to call, which the search's chaotic landscape turned into different
    answers); rows where A is not numerically positive definite fall back to least squares."""
    chol, info = torch.linalg.cholesky_ex(A)
    x = torch.cholesky_solve(b.unsqueeze(-1), chol).squeeze(-1)
    bad = info != 0
    if bool(bad.any()):
        x[bad] = torch.linalg.lstsq(A[bad], b[bad].unsqueeze(-1)).solution.squeeze(-1)
    return x


def laplace_draws(post, modes: list, count: int, *, seed: int, scales=(1.0, 2.0)) -> torch.Tensor:
    """``count`` draws (count, P) about an earlier stage's modes, for the next stage's screen: from
    each mode's Laplace approximation under ``post`` (the stage's posterior: N(x, s^2 (J^T J)^-1),
    s alternating over ``scales``), half of them about the best mode, the rest shared by the next
    three. Where the next sighting follows a tumble, the stage's modes explain it poorly (a box
    tracked at six moments: its fifth stage's best mode cost 220 with the sixth sighting, its truth
    25), while draws within the stage's uncertainty, refined, reach it (21.7 from 400 draws)."""
    if not modes:
        return torch.zeros(0, post.layout.size, dtype=torch.float64)
    gen = torch.Generator().manual_seed(int(seed) * 104729 + 17)
    top = modes[:4]
    shares = [count // 2] + [(count - count // 2) // max(1, len(top) - 1)] * (len(top) - 1) if len(top) > 1 else [count]
    x = torch.stack([m.x.to(torch.float64) for m in top])
    _, J = post.jacobian(x)
    out = [x[:0]]
    for i, n in enumerate(shares):
        H = J[i].T @ J[i]
        H = H + 1e-9 * float(torch.diagonal(H).mean().clamp_min(1e-12)) * torch.eye(H.shape[0], dtype=H.dtype)
        R, info = torch.linalg.cholesky_ex(H)
        if int(info) != 0 or not bool(torch.isfinite(R).all()):
            continue  # no curvature to draw from (a non-finite Jacobian): the mode itself seeds
        L, info = torch.linalg.cholesky_ex(torch.cholesky_inverse(R))
        if int(info) != 0:
            continue
        scale = torch.tensor([scales[j % len(scales)] for j in range(n)], dtype=torch.float64)[:, None]
        out.append(x[i] + scale * (torch.randn(n, x.shape[1], generator=gen, dtype=torch.float64) @ L.T))
    return torch.cat(out)


def stages(post) -> list[tuple]:
    """The earlier stages of a tracked source's search (``MapSearch.run``): the sightings up to each
    observed moment but the last, in time order; none where fewer than two moments were observed
    or a sighting takes the best record of all."""
    steps = sorted({sg.step for sg in post.sightings if sg.step is not None})
    if len(steps) < 2 or any(sg.step is None for sg in post.sightings):
        return []
    return [tuple(sg for sg in post.sightings if sg.step <= k) for k in steps[:-1]]


class MapSearch:
    """The search for the most probable past (module docstring), with its ``SearchParams``.

    ``MapSearch(SearchParams(budget=20000)).run(posterior)`` -> ``SearchResult``.
    """

    def __init__(self, params: SearchParams | None = None):
        self.params = SearchParams() if params is None else params

    def run(self, post, *, callback=None, should_stop=None, seeds: torch.Tensor | None = None) -> SearchResult:
        """The most probable start under ``post`` (a ``dejaview.inference.posterior.Posterior``).

        A tracked source (several observed moments, ``stages``) is searched in time order: the
        likelihood of its first observations alone reads short rollouts, before most contacts (a
        toss's first two positions fix its throw), and is far smoother than that of all of them,
        whose end follows a tumble and a rest. So each earlier stage explains the observations up
        to its moment (``stage_share`` of the iterations and budget each; their rollouts stop
        there, and count by their length: a rollout to 0.1 s of 0.9 s spends a ninth of one) and
        seeds the next stage's instances with its modes, beside fresh prior draws. The last stage
        takes what is left, and at least ``last_share`` of both.
        Under model uncertainty (``post.model``) the global search runs on the scene's own
        physics and its modes are refined and ranked under the variants
        (``refine_under_variants``).

        Args:
            callback: called with a ``Progress`` after every iteration (``loss``: the iteration's
                best negative log posterior, ``best_loss`` the best so far, ``evaluations`` budget
                units spent; iterations numbered over all stages).
            should_stop: polled after every iteration; True ends the search with its best so far.
            seeds: (K, P) starts the first stage's instances take first, before the screened ones
                (an amortised posterior's best draws).
        Returns:
            SearchResult; ``x`` the best parameters (P,), ``loss`` the scene's loss there (metres),
            ``rollouts`` and ``history`` over all stages.
        """
        from dataclasses import replace

        p = self.params
        plain = post.without_model() if post.model is not None else post
        history, spent, rollouts, jacobians = [], 0, 0, 0
        offset = used = 0

        def report(progress):
            if callback is not None:
                callback(replace(progress, iteration=progress.iteration + offset))

        steps, near = plain.problem.steps, None
        for prefix in stages(plain):
            part = plain.restricted(prefix)
            length = part.problem.steps / steps  # its rollouts' share of a whole one's steps
            found = self._stage(part, replace(p, iterations=max(1, int(p.stage_share * p.iterations)),
                                              budget=max(1, int(p.stage_share * p.budget / length)), tolerance=None),
                                report, should_stop, seeds, near)
            spent += length * (found.rollouts + p.jacobian_cost * found.jacobians)
            rollouts, jacobians = rollouts + found.rollouts, jacobians + found.jacobians
            used += length * sum(q.phase != "refine" for q in found.history)
            history += found.history
            offset = len(history)
            if found.stopped:
                break
            seeds = torch.stack([m.x for m in found.modes])
            near = laplace_draws(part, found.modes, screen_size(part.layout.size), seed=p.seed + len(history))
            drawn = part.jacobians - found.jacobians  # laplace_draws' Jacobians
            jacobians += drawn
            spent += length * p.jacobian_cost * drawn
        final = self._stage(plain, replace(p, iterations=max(int(p.last_share * p.iterations), int(p.iterations - used)),
                                           budget=max(int(p.last_share * p.budget), int(p.budget - spent))),
                            report, should_stop, seeds, near)
        for q in final.history:
            q.iteration += offset
        final.history = history + final.history
        final.rollouts += rollouts
        final.jacobians += jacobians
        if post.model is not None and not final.stopped:
            final = refine_under_variants(post, final, params=p, callback=callback, should_stop=should_stop)
        return final

    @staticmethod
    def _stage(post, params: SearchParams, callback, should_stop, seeds, near=None) -> SearchResult:
        """One search over all of ``post``'s sightings; ``seeds`` (K, P): starts the instances take
        first (an earlier stage's modes); ``near`` (N, P): draws about them, ranked with them."""
        s = _Search(post, params, callback, should_stop, seeds, near)
        s.run()
        best = s.best
        if s.modes and s.modes[0].cost <= best.cost:
            best = s.modes[0]
        modes = s.modes or [best]
        return SearchResult(x=best.x, loss=best.loss, history=s.history, best_index=0, stopped=s.stopped,
                            candidate_x=torch.stack([m.x for m in modes]),
                            candidate_loss=torch.tensor([m.loss for m in modes], dtype=torch.float64),
                            cost=best.cost, chi2=best.chi2, modes=modes, rollouts=post.rollouts,
                            jacobians=post.jacobians)


def refine_under_variants(post, found, *, params=None, callback=None, should_stop=None):
    """The search's answer under model uncertainty: its modes refined and re-ranked on ``post``.

    The global stage (``MapSearch``) runs on the scene's own physics: one rollout per candidate,
    and it stops once a candidate explains the end, which under model uncertainty none does (the
    variants' spread is a floor), so a global search on the averaged likelihood ran to its
    patience (``docs/physics-fidelity.md`` has the measured cost). Its distinct modes (``found.modes``, best first,
    and its best) are instead refined by Levenberg-Marquardt on the averaged likelihood of
    ``post`` (exact Jacobians through every variant) and ranked by the averaged likelihood under
    held-out variants (``rank_on_heldout``): a needle past, whose end moves when the friction
    does, loses to one whose end holds, also where it happened to fit the variants it was
    refined on. Where the first of them does not explain the end under the held-out variants
    (``explains_end``: every past fitted on the scene's own physics was a needle), the search's
    other modes, up to ``params.candidates`` of those with the lowest cost on ``post`` (unrefined, no
    Jacobians), are refined too and all are ranked again.

    Args:
        post: ``Posterior`` with ``model`` set.
        found: ``SearchResult`` of the search on the scene's physics.
        params: the search's ``SearchParams`` (``lm_final_iterations``: most LM iterations of each
            refinement; ``seed`` draws the held-out variants; ``candidates``).
    Returns:
        ``SearchResult`` on ``post`` (cost, chi2 and modes under model uncertainty, ranked on the
        held-out variants), history appended to ``found``'s.
    """
    from dataclasses import replace

    from dejaview.inference.model_uncertainty import explains_end, rank_on_heldout

    params = SearchParams() if params is None else params
    iterations, seed, candidates = params.lm_final_iterations, params.seed, params.candidates
    s = _Search(post, replace(params, iterations=max(1, iterations + len(found.history)), budget=10 ** 12,
                              tolerance=None), callback, should_stop)
    s.history = list(found.history)
    s.n_obs = max(1, post.num_observed)
    starts = [found.x] + [m.x for m in found.modes if float((m.x - found.x).norm()) > 0][:candidates - 1]
    s.add_modes(s.refine(torch.stack(starts).to(torch.float64), iterations))
    heldout_rollouts = 0
    if not s.stopped:  # a cancelled solve returns at once, its modes as the refinement ranked them
        s.modes, heldout_rollouts = rank_on_heldout(post, s.modes, seed)
    others = [m.x for m in found.modes if all(float((m.x - y).norm()) > 0 for y in starts)]
    if not s.stopped and others and s.modes and not explains_end(post, s.modes[0]):
        cost = post.cost(torch.stack(others).to(torch.float64))[0]
        order = [i for i in torch.argsort(cost, stable=True).tolist() if math.isfinite(float(cost[i]))]
        if order:
            s.iterations = len(s.history) + iterations  # the second refinement's own iterations
            s.add_modes(s.refine(torch.stack([others[i] for i in order[:candidates]]).to(torch.float64),
                                 iterations))
            if not s.stopped:
                s.modes, spent = rank_on_heldout(post, s.modes, seed)
                heldout_rollouts += spent
    best = s.modes[0] if s.modes else s.best
    return SearchResult(x=best.x, loss=best.loss, history=s.history, best_index=0, stopped=s.stopped,
                        candidate_x=torch.stack([m.x for m in s.modes or [best]]),
                        candidate_loss=torch.tensor([m.loss for m in s.modes or [best]], dtype=torch.float64),
                        cost=best.cost, chi2=best.chi2, modes=s.modes or [best],
                        rollouts=found.rollouts + post.rollouts + heldout_rollouts,
                        jacobians=found.jacobians + post.jacobians)
