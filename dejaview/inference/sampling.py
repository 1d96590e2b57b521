"""Posterior samples: every past that explains the end, weighted by its probability.

``Sampler(SamplerParams()).sample(post, modes, n)`` draws ``n`` samples of the free parameters
x from the posterior of ``dejaview.inference.posterior`` (likelihood of the
observed end times the prior), starting from the modes that the most-probable-
past search (``dejaview.inference.search``) found.

The target density over x (``dejaview.inference.reference.log_density``) is
``-0.5 |R(x)|^2`` plus the log density of the parameterisation's base measure;
infeasible starts and non-finite rollouts have density 0.

The sampler is sequential Monte Carlo (Del Moral, Doucet and Jasra 2006) with
likelihood tempering: particles drawn from the prior (``prior_draws``) are
carried to the posterior through ``pi_beta(x) ~ prior(x) L(x)^beta``, beta from
0 to 1 (where the prior is improper, a position free without a start area, the
bridge starts from the mixture q below instead of the prior).

- beta advances as far as keeps the effective sample size of the incremental
  weights at ``ess_fraction`` of the particles (bisection), then the particles
  are resampled (systematic) and moved by Metropolis-Hastings kernels that
  leave pi_beta invariant:
  - one independence move proposing from q, a mixture of multivariate
    Student-t distributions (``SamplerParams.reference_df`` degrees of freedom) centred on the MAP
    search's distinct modes with the Laplace covariance of each
    (``(J^T J + C)^-1`` from the exact residual Jacobian J and the curvature C
    of the base measure and flat priors), weighted by its Laplace evidence
    ``p(m) sqrt(det Sigma)``, plus the prior itself (``prior_share``): the
    particles jump into every mode the search found, in proportion to its mass;
  - ``rw_moves`` random-walk moves whose step covariance is that of the
    population in the particle's mode (the particles the same reference
    component is most responsible for; the step scale adapts towards
    ``target_acceptance``), every other one a differential-evolution step
    ``x + g (x_a - x_b)`` between two other particles, whose length follows the
    population's extent (long along a ridge the end leaves free). Both walk a
    start-area position as its fraction of the area (``_SMC.to_walk``), and
    the particles move in two halves, each guided by the other half's current
    values (``_SMC.halves``): a kernel built from the particles that move with
    it is not exact. The first of them each step is a population move
    (``population_moves``): an independence proposal from a kernel density
    estimate of the other half, so particles jump between the basins the
    population holds and the basins' shares follow their mass, where the walks
    stay in their basin.
  - Where the scene has a symmetry (``dejaview.inference.symmetry``: a floor and nothing else
    static, the source alone, its end compared at one record; ``symmetry_moves``), each step
    also moves every particle along its orbit (the start moved and turned so that its end lands
    on the observed one, drawn by conditional importance sampling over such motions), and the
    random-walk and differential-evolution steps act on the coordinates the motions leave alone,
    accepted by the orbits' integrals (pseudo-marginal), so a walk is not undone by an end that
    lands a few centimetres or degrees off.
- A tracked source (targets at several moments, ``sighting_chain``) is bridged sighting after
  sighting: from the prior to the posterior of its first moment's observations, from that to the
  first two moments', and so on to all of them (each bridge ``(1 - beta) log p_(k-1) + beta log
  p_k``, its rollouts stopping at the k-th moment). A toss's first positions read rollouts in
  flight, before any contact, which cost a fraction of a whole one; the bridge reaches the
  tumble's sightings with particles already where the throw was.
- At beta = 1 the moves go on until ``final_moves`` have run there.
- Each run estimates the log evidence (``stats["log_evidence"]``: the sum over its steps of the
  log mean incremental weight; log of the integral of ``exp(log_density)``): runs that disagree
  but estimate alike hold branches of like mass; one far above the other found more of it.
- The n samples are those of ``runs`` independent runs (n / runs particles
  each, seeds apart; below ``particles`` samples a random n / runs of each
  run's twice as many): where they disagree (``posterior_report.rhat``) the
  posterior is rugged, each run holds other branches of it, and the report
  says so (measured on the calibration bench: docs/inference.md).

Tempering from the prior reaches branches of the posterior the search did not
find (a ball thrown up rather than rolled, both ending alike); the moves from
q make the known modes cheap to reach. Why this and not NUTS or plain
importance sampling around the modes: see docs/inference.md ("The
posterior"), measured with ``dejaview bench calibration``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch

from dejaview.errors import InferenceError
from dejaview.inference.params import SamplerParams
from dejaview.inference.population import adapted, chol_of, difference_steps, ess, from_walk, systematic, to_walk
from dejaview.inference.reference import Mixture, laplace_mixture, log_density, log_prior_density, prior_draws
from dejaview.inference.symmetry import FloorSymmetry, assign, orbit_walk

@dataclass
class PosteriorSamples:
    """Weighted samples of the posterior.

    Attributes:
        x: (N, P) parameters; weights: (N,) non-negative, summing to 1; log_density: (N,).
        component: (N,) the mode each sample belongs to: the nearest of the search's distinct
            modes (the reference components' centres), in scaled parameters.
        mode_index: per component, the index of the search mode it is centred on.
        run: (N,) which of the sampler's independent runs (``runs``) drew each sample.
        stats: what the sampler did (stages, betas, acceptance, ESS, rollouts, seconds).
    """

    x: torch.Tensor
    weights: torch.Tensor
    log_density: torch.Tensor
    component: torch.Tensor
    mode_index: list
    run: torch.Tensor | None = None
    stats: dict = field(default_factory=dict)


def particles(n: int, params: SamplerParams | None = None) -> list[int]:
    """The particles of each independent run (``SamplerParams.runs``) that draw n samples."""
    p = SamplerParams() if params is None else params
    m = max(n, min(p.particles, 2 * n))
    return _shares(m, p.runs if m >= p.runs * p.min_run_size else 1)


def _shares(total: int, parts: int) -> list[int]:
    """``total`` split into ``parts`` near-equal counts, the first ones one more."""
    return [total // parts + (1 if i < total % parts else 0) for i in range(parts)]


def sighting_chain(post) -> list:
    """The posteriors a tracked source's bridge passes through before ``post``: those of its
    sightings up to each observed moment but the last (``search.stages``), on the scene's own
    physics; none for a source seen once (or a posterior that is not a scene's)."""
    if not hasattr(post, "restricted"):
        return []
    from dejaview.inference.search import stages

    plain = post.without_model() if post.model is not None else post
    return [plain.restricted(prefix) for prefix in stages(plain)]


class _SMC:
    """State of one run of ``Sampler.sample``; its methods are the named steps."""

    def __init__(self, post, q: Mixture, n: int, seed: int, callback, should_stop, from_prior: bool,
                 params: SamplerParams, chain: list | None = None):
        self.p = params
        self.post, self.q, self.n = post, q, n
        self.chain = list(chain or []) + [post]
        self.level = 0
        """The bridge runs from ``chain[level - 1]`` (the reference at level 0) to ``chain[level]``."""
        self.from_prior = from_prior
        self.gen = torch.Generator().manual_seed(int(seed) * 104729 + 17)
        self.callback, self.should_stop = callback, should_stop
        self.beta = 0.0
        self.scale = 2.38 / math.sqrt(max(post.layout.size, 1))
        self.stages = 0
        self.log_z = 0.0
        """The run's estimate of the log evidence (up to the reference's constant)."""
        self.moves = 0
        self.acceptance: list[float] = []
        self.ess_steps: list[float] = []
        self.t0 = time.perf_counter()
        self.symmetry = (FloorSymmetry.of(post, params.orbit_width)
                         if params.symmetry_moves and len(self.chain) == 1 else None)
        self.orbit_scale = self.scale
        self.ends, self.ends_known = None, None
        """The compared records of the particles' rollouts, and which of them hold (``orbit_walk``)."""

    def reference(self, x: torch.Tensor) -> torch.Tensor:
        """Log density (B,) of the bridge's start: the prior, or the mixture q; at a later level the
        posterior of the sightings before it."""
        if self.level > 0:
            return log_density(self.chain[self.level - 1], x, feasibility=False)
        return log_prior_density(self.post, x) if self.from_prior else self.q.log_prob(x)

    @property
    def here(self):
        """The posterior the bridge runs to now."""
        return self.chain[self.level]

    def start(self) -> None:
        if self.from_prior:
            self.x = prior_draws(self.post, self.n, self.gen)
        else:
            self.x, _ = self.q.sample(self.n, self.gen)
        self.lr = self.reference(self.x)
        self.lq = self.q.log_prob(self.x)
        self.lp = log_density(self.here, self.x)
        if not bool(torch.isfinite(self.lp).any()):
            raise InferenceError("no draw from the prior or around the modes has a finite posterior density")

    def stopped(self) -> bool:
        return self.should_stop is not None and bool(self.should_stop())

    def report(self) -> None:
        if self.callback is not None:
            self.callback({"beta": self.beta, "stage": self.stages, "moves": self.moves,
                           "fraction": 1.0 if self.beta >= 1.0 and self.level == len(self.chain) - 1
                           else 0.9 * (self.level + self.beta) / len(self.chain),
                           "elapsed_s": time.perf_counter() - self.t0})

    def temper(self) -> None:
        """Advance beta as far as keeps ``ess_fraction`` of the particles; resample."""
        d = torch.where(torch.isfinite(self.lp), self.lp - self.lr, torch.full_like(self.lp, -math.inf))
        target = self.p.ess_fraction * self.n
        if ess((1.0 - self.beta) * d) >= target:
            new = 1.0
        else:
            lo, hi = self.beta, 1.0
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                if ess((mid - self.beta) * d) >= target:
                    lo = mid
                else:
                    hi = mid
            new = max(lo, self.beta + 1e-6)
        logw = (new - self.beta) * d
        self.ess_steps.append(ess(logw))
        self.log_z += float(torch.logsumexp(logw, 0)) - math.log(self.n)
        self.beta = new
        idx = systematic(logw, self.gen)
        self.x, self.lr, self.lq, self.lp = self.x[idx], self.lr[idx], self.lq[idx], self.lp[idx]
        if self.ends is not None:
            self.ends, self.ends_known = [t.select(idx) for t in self.ends], self.ends_known[idx]
        self.stages += 1
        if self.beta >= 1.0 and self.level < len(self.chain) - 1:  # on to the next sighting
            self.level += 1
            self.lr, self.beta = self.lp, 0.0
            self.lp = log_density(self.here, self.x, feasibility=False)

    def target(self, lr: torch.Tensor, lp: torch.Tensor) -> torch.Tensor:
        """log pi_beta = (1 - beta) log r + beta log p (``-inf`` where p is 0)."""
        out = (1.0 - self.beta) * lr + self.beta * lp if self.beta < 1 else lp.clone()
        return torch.where(torch.isfinite(lp) & ~torch.isnan(out), out, torch.full_like(out, -math.inf))

    def metropolis(self, y: torch.Tensor, rows: torch.Tensor, log_q_ratio: torch.Tensor | None = None,
                   independence: bool = False) -> float:
        """Accept or reject proposals y (R, P) for the particles ``rows`` (R,) by Metropolis-Hastings:
        the log acceptance ratio is ``log pi_beta(y) - log pi_beta(x)`` plus ``log_q_ratio`` (R,)
        (``log q(x | y) - log q(y | x)``; None: a symmetric proposal), or for an ``independence``
        proposal from the mixture q, ``log q(x) - log q(y)``.

        The proposals are simulated as if feasible, and the interpenetration check (fcl, as
        costly as a rollout) runs only on those the ratio would accept: an infeasible start
        has density 0, which can only turn an acceptance into a rejection. Same decisions as
        checking every proposal first (the uniform draws do not depend on the values).
        Returns the acceptance rate."""
        u = torch.rand(rows.shape[0], generator=self.gen, dtype=torch.float64)
        lr_x, lq_x, lp_x = self.lr[rows], self.lq[rows], self.lp[rows]
        lq_y = self.q.log_prob(y)
        lp_y = torch.full_like(u, -math.inf)
        live = torch.ones_like(u, dtype=torch.bool) if log_q_ratio is None else torch.isfinite(log_q_ratio)
        if self.level == 0:  # the prior's or q's density: no rollout, taken for every row as before
            lr_y = self.reference(y)
        else:
            lr_y = torch.full_like(u, -math.inf)
            if bool(live.any()):
                lr_y[live] = self.reference(y[live])
        if bool(live.any()):  # a proposal the Hastings term rules out (outside the area) is not simulated
            lp_y[live] = log_density(self.here, y[live], feasibility=False)
        log_ratio = self.target(lr_y, lp_y) - self.target(lr_x, lp_x)
        if independence:
            log_ratio = log_ratio + (lq_x - lq_y)
        elif log_q_ratio is not None:
            log_ratio = log_ratio + log_q_ratio
        ok = torch.isfinite(log_ratio) & (torch.log(u) < log_ratio)
        if bool(ok.any()):  # density 0 where infeasible: rejected
            idx = ok.nonzero().squeeze(-1)
            bad = idx[~self.post.feasible(y[idx])]
            lp_y[bad] = -math.inf
            ok[bad] = False
        if self.ends is not None:  # their rollouts' ends (``orbit_walk``) are now unknown
            self.ends_known[rows[ok]] = False
        self.x[rows] = torch.where(ok[:, None], y, self.x[rows])
        self.lr[rows] = torch.where(ok, lr_y, lr_x)
        self.lq[rows] = torch.where(ok, lq_y, lq_x)
        self.lp[rows] = torch.where(ok, lp_y, lp_x)
        return float(ok.double().mean())

    def independence_move(self) -> float:
        """Propose from the mixture q (jumps between the search's modes)."""
        y, _ = self.q.sample(self.n, self.gen)
        acc = self.metropolis(y, torch.arange(self.n), independence=True)
        self.moves += 1
        return acc

    def orbit_move(self) -> float:
        """A move along each particle's orbit under the scene's symmetry (``symmetry.orbit_walk``
        without a step: its end carried onto the observed one); one rollout per particle."""
        y, lp, moved, ends = orbit_walk(self.post, self.symmetry, self.x, self.tempered, self.beta, self.gen,
                                        draws=self.p.orbit_draws, known=self.known(torch.arange(self.n)))
        self.x, self.lp = y, lp
        self.lr, self.lq = self.reference(y), self.q.log_prob(y)
        self.ends, self.ends_known = ends, torch.ones(self.n, dtype=torch.bool)
        self.moves += 1
        return float(moved.double().mean())

    def known(self, rows: torch.Tensor) -> tuple | None:
        """The known ends of the particles ``rows`` for ``orbit_walk``, or None."""
        if self.ends is None:
            return None
        return [t.select(rows) for t in self.ends], self.ends_known[rows]

    def tempered(self, y: torch.Tensor, lp: torch.Tensor) -> torch.Tensor:
        """log pi_beta (B,) of parameters y (B, P) whose log posterior density is lp (B,)."""
        return self.target(self.reference(y), lp)

    def orbit_walk_move(self, difference: bool) -> float:
        """Across orbits (``symmetry.orbit_walk`` with a step in the orbit coordinates r): a normal
        step with the guides' covariance of r (``halves``), or with ``difference`` a
        differential-evolution step between two guides; a rollout per particle (and of its own
        start where its end is not known)."""
        sym, lay = self.symmetry, self.post.layout
        accepted = 0.0
        for rows, guides in self.halves():
            gr = torch.unique(sym.coordinates(lay, self.x[guides])[0], dim=0)
            r = rows.shape[0]
            if difference and gr.shape[0] >= 2:
                step = sum(difference_steps(gr, r, self.gen))
            else:
                z = torch.randn((r, gr.shape[1]), generator=self.gen, dtype=torch.float64)
                step = self.orbit_scale * (z @ chol_of(gr).T)
            y, lp, ok, ends = orbit_walk(self.post, sym, self.x[rows], self.tempered, self.beta, self.gen,
                                         step=step, draws=self.p.orbit_draws, known=self.known(rows))
            self.x[rows], self.lp[rows] = y, lp
            if self.ends is not None:
                self.ends = assign(self.ends, rows, ends)
                self.ends_known[rows] = True
            self.lr[rows], self.lq[rows] = self.reference(y), self.q.log_prob(y)
            accepted += float(ok.double().sum())
        self.moves += 1
        acc = accepted / self.n
        if not difference:
            self.orbit_scale = adapted(self.orbit_scale, acc, self.p.target_acceptance)
        return acc

    def halves(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """A random split of the particles into two halves, as (moved, guides) twice: each half
        moves in turn with the other half's current values as its fixed guides.

        Why: a kernel built from the population (nearest neighbours, differences of members)
        leaves the target invariant only for guides that stay fixed while the particle moves.
        Moving every particle at once, each guided by the others' old values, does not: on an
        11-D Gaussian the walk settled at 0.8 of the true variance. The
        halves' alternation is exact (as in Goodman and Weare's ensemble samplers) and costs
        the same rollouts."""
        perm = torch.randperm(self.n, generator=self.gen)
        a, b = perm[: self.n // 2], perm[self.n // 2:]
        return [(a, b), (b, a)]

    def mode_of(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) the reference component (one of the search's distinct modes) most responsible for
        parameters x (B, P), the prior component left out: a fixed partition of the space."""
        k = self.q.means.shape[0]
        return self.q.component_log_prob(x)[:, :k].argmax(-1)

    def mode_chol(self, w: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
        """(K, P, P) Cholesky factors of the covariance of the guides at walk coordinates w (M, P)
        (``to_walk``) that each reference component is most responsible for (``own`` (M,):
        ``mode_of`` the guides); the guides' overall covariance for a component with fewer
        than P + 2.

        Why per mode and not of the nearest neighbours: a posterior that the end pins in a few
        directions and leaves to the prior in the others is a thin slab; a point's nearest
        neighbours span a small patch of it, so steps along the slab stay short and the
        population, thinned there by every resampling, never spreads again (on an 11-D
        Gaussian with 6 observed directions: central 90 % intervals held the truth 46 % of
        the time with nearest-neighbour steps alone, 86 % with the population's covariance)."""
        k, p = self.q.means.shape[0], w.shape[1]
        out = chol_of(w).expand(k, p, p).clone()
        for j in range(k):
            mine = own == j
            if int(mine.sum()) >= p + 2:
                out[j] = chol_of(w[mine])
        return out

    def to_walk(self, x: torch.Tensor) -> torch.Tensor:
        """``population.to_walk`` on this posterior's layout."""
        return to_walk(self.post.layout, x)

    def from_walk(self, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``population.from_walk`` on this posterior's layout."""
        return from_walk(self.post.layout, w)

    def walk_log_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """``log |dx/dw|`` (B,) at parameters x (B, P) (``to_walk``)."""
        return self.from_walk(self.to_walk(x))[1]

    def walk_metropolis(self, rows: torch.Tensor, w_y: torch.Tensor, log_q_ratio: torch.Tensor | None) -> float:
        """Metropolis-Hastings for a proposal made in walk coordinates w_y (R, P) with the walk's
        log Hastings term ``log_q_ratio`` (R,) (None: symmetric): the target in walk coordinates
        is the one in parameters times ``|dx/dw|``; proposals outside the start area are
        rejected without a rollout."""
        y, log_jac_y = self.from_walk(w_y)
        ratio = log_jac_y - self.walk_log_jacobian(self.x[rows])
        if log_q_ratio is not None:
            ratio = ratio + log_q_ratio
        inside = torch.isfinite(log_jac_y)
        y = torch.where(inside[:, None], y, self.x[rows])
        return self.metropolis(y, rows, ratio)

    def random_walk_move(self) -> float:
        """w = to_walk(x); w' = w + scale * L z, L the Cholesky factor of the covariance of the
        guides (the other half of the particles, ``halves``) in x's mode (``mode_chol``), in walk
        coordinates; the Hastings ratio uses the factor of the mode at w'."""
        accepted = 0.0
        for rows, guides in self.halves():
            gx = torch.unique(self.x[guides], dim=0)
            chol = self.mode_chol(self.to_walk(gx), self.mode_of(gx))
            lx = chol[self.mode_of(self.x[rows])]
            here = self.to_walk(self.x[rows])
            z = torch.randn(here.shape, generator=self.gen, dtype=torch.float64)
            w_y = here + self.scale * (lx @ z.unsqueeze(-1)).squeeze(-1)
            y, _ = self.from_walk(w_y)
            ly = chol[self.mode_of(y)]
            back = torch.linalg.solve_triangular(ly, (here - w_y).unsqueeze(-1) / self.scale,
                                                 upper=False).squeeze(-1)
            logdet_x = torch.log(torch.diagonal(lx, dim1=-2, dim2=-1)).sum(-1)
            logdet_y = torch.log(torch.diagonal(ly, dim1=-2, dim2=-1)).sum(-1)
            log_q_ratio = (-0.5 * (back * back).sum(-1) - logdet_y) - (-0.5 * (z * z).sum(-1) - logdet_x)
            accepted += self.walk_metropolis(rows, w_y, log_q_ratio) * rows.shape[0]
        self.moves += 1
        acc = accepted / self.n
        self.scale = adapted(self.scale, acc, self.p.target_acceptance)
        return acc

    def population_move(self) -> float:
        """Independence proposal from a kernel density estimate of the guides (the other half of
        the particles, ``halves``), in walk coordinates: a guide drawn at random, plus a normal
        step with its mode's covariance (``mode_chol``) times Silverman's bandwidth factor. A
        particle can jump into any basin the other half holds, in proportion to how many
        guides sit there; the Hastings ratio q(w) / q(w') weighs basins by their mass."""
        p = self.x.shape[1]
        accepted = 0.0
        for rows, guides in self.halves():
            gx = torch.unique(self.x[guides], dim=0)
            m = gx.shape[0]
            if m == 0 or rows.shape[0] == 0:  # a population of one: nothing to propose from
                continue
            h = (4.0 / ((p + 2) * m)) ** (1.0 / (p + 4))
            g = self.to_walk(gx)
            own = self.mode_of(gx)  # (M,)
            chol = self.mode_chol(g, own) * h  # (K, P, P)
            gl = chol[own]  # (M, P, P)
            inv = torch.linalg.inv(chol)  # (K, P, P)
            logdet = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)  # (K,)

            def log_kde(w, inv=inv, own=own, g=g, logdet=logdet, chunk=self.p.kde_rows):
                """(R,) log density (up to a constant) of the estimate at walk coordinates w (R, P),
                ``chunk`` rows at a time (0: all): each row's sum is its own, so chunks change
                no number beyond round-off."""
                parts = []
                for wc in w.split(chunk or max(w.shape[0], 1)):
                    out = torch.full((wc.shape[0], g.shape[0]), -math.inf, dtype=w.dtype)
                    for c in range(inv.shape[0]):
                        mine = own == c
                        if bool(mine.any()):  # the kernels of component c's guides, whitened by its factor
                            d = torch.cdist(wc @ inv[c].T, g[mine] @ inv[c].T)
                            out[:, mine] = -0.5 * d * d - logdet[c]
                    parts.append(torch.logsumexp(out, -1))
                return torch.cat(parts)

            r = rows.shape[0]
            pick = torch.randint(m, (r,), generator=self.gen)
            z = torch.randn((r, p), generator=self.gen, dtype=torch.float64)
            w_y = g[pick] + (gl[pick] @ z.unsqueeze(-1)).squeeze(-1)
            ratio = log_kde(self.to_walk(self.x[rows])) - log_kde(w_y)
            accepted += self.walk_metropolis(rows, w_y, ratio) * r
        self.moves += 1
        return accepted / self.n

    def difference_move(self) -> float:
        """Differential-evolution step (ter Braak 2006) in walk coordinates: w' = w + g (w_a - w_b)
        + e, a and b two distinct guides (members of the other half of the particles,
        ``halves``), g = 2.38 / sqrt(2 P), e a jitter of 1e-4 of the guides' spread: the step
        follows the population's own extent and direction (along a ridge the end leaves free).
        Symmetric given the guides."""
        splits = self.halves()
        # fewer than two distinct guides on a side: a random walk instead (decided before either
        # half moves; a move never merges distinct values, so the count holds for the second half)
        if min(torch.unique(self.x[guides], dim=0).shape[0] for _, guides in splits) < 2:
            return self.random_walk_move()
        accepted = 0.0
        for rows, guides in splits:
            population = torch.unique(self.to_walk(self.x[guides]), dim=0)
            r = rows.shape[0]
            d, e = difference_steps(population, r, self.gen)
            y = self.to_walk(self.x[rows]) + d + e
            accepted += self.walk_metropolis(rows, y, None) * r
        self.moves += 1
        return accepted / self.n

    def distinct(self) -> float:
        return torch.unique(self.x, dim=0).shape[0] / self.n

    def move(self, count: int) -> None:
        """One independence move, then random-walk moves, ``count`` in all, and more (up to
        ``MAX_MOVES``) while fewer than ``DISTINCT_FRACTION`` of the particles are distinct."""
        self.acceptance.append(self.independence_move())
        if self.symmetry is not None:
            self.acceptance.append(self.orbit_move())
        done = 1
        while done < count or (done < self.p.max_moves and self.distinct() < self.p.distinct_fraction):
            if self.stopped():
                return
            if self.p.population_moves and done == 1:
                self.acceptance.append(self.population_move())
            elif self.symmetry is not None:
                self.acceptance.append(self.orbit_walk_move(difference=self.p.difference_moves and done % 2 == 0))
            else:
                self.acceptance.append(self.difference_move() if self.p.difference_moves and done % 2 == 0
                                       else self.random_walk_move())
            done += 1

    def finished(self) -> bool:
        return self.beta >= 1.0 and self.level == len(self.chain) - 1

    def run(self) -> None:
        self.start()
        self.report()
        while not self.finished() and self.stages < self.p.max_stages:
            if self.stopped():
                raise InferenceError("stopped while sampling the posterior")
            self.temper()
            self.move(self.p.final_moves if self.finished() else 1 + self.p.rw_moves)
            self.report()
        if not self.finished():
            raise InferenceError(f"the posterior sampler did not reach the posterior in {self.p.max_stages} steps")


class Sampler:
    """The posterior sampler (module docstring), with its ``SamplerParams``.

    ``Sampler(SamplerParams(seed=1)).sample(posterior, modes, n)`` -> ``PosteriorSamples``.
    """

    def __init__(self, params: SamplerParams | None = None):
        self.params = SamplerParams() if params is None else params

    def sample(self, post, modes: list, n: int, *, callback=None, should_stop=None, proposal=None,
               proposal_share: float = 0.5) -> PosteriorSamples:
        """Draw n weighted samples from the posterior ``post`` (module docstring).

        Args:
            post: a ``dejaview.inference.posterior.Posterior``.
            modes: the search's modes (``SearchResult.modes``: ``Mode`` with x (P,) and cost), best first.
            n: number of samples (>= 1).
            callback: called with a dict (``beta``, ``stage``, ``moves`` of the current run, ``run``
                (its index), ``fraction`` (0 to 1: how far the sampler is over all runs),
                ``elapsed_s``) after each run's start and every tempering step.
            should_stop: polled between moves; True raises InferenceError (nothing half-sampled is
                returned).
            proposal: optional ``sample(n, gen)`` / ``log_prob(x)`` object (an amortised posterior at
                the observation) made a component of the reference mixture with weight
                ``proposal_share``: the independence moves propose from it.
        Returns:
            PosteriorSamples; equal weights 1/n after the final moves.
        """
        p = self.params
        seed = p.seed
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise InferenceError(f"samples must be a positive integer, got {n!r}")
        if post.layout.size == 0:
            raise InferenceError("the posterior has no free parameter to sample: free one in <optimize>")
        rollouts0 = post.rollouts
        q, mode_index = laplace_mixture(post, modes, p)
        proper = post.layout.lo is not None or post.layout.block_slice("position").stop == 0
        if proper:  # the prior is a proper distribution: temper from it, propose from it too
            q.prior, q.prior_share = post, p.prior_share
        if proposal is not None:
            q.flow, q.flow_share = proposal, float(proposal_share)
        chain = sighting_chain(post) if p.sightings else []
        sizes = particles(n, p)
        m, keep = sum(sizes), _shares(n, len(sizes))
        t0 = time.perf_counter()
        runs = []
        for i, size in enumerate(sizes):
            def report(info, i=i):
                if callback is not None:
                    callback({**info, "fraction": (i + info["fraction"]) / len(sizes), "run": i,
                              "elapsed_s": time.perf_counter() - t0})
            smc = _SMC(post, q, size, seed + 7919 * i, report, should_stop, from_prior=proper, params=p,
                       chain=chain)
            smc.run()
            runs.append(smc)
        pick = torch.Generator().manual_seed(int(seed) * 7 + 3)
        rows = [torch.randperm(r.n, generator=pick)[:k].sort().values for r, k in zip(runs, keep)]
        x = torch.cat([r.x[i] for r, i in zip(runs, rows)])
        lp = torch.cat([r.lp[i] for r, i in zip(runs, rows)])
        run = torch.cat([torch.full((k,), i, dtype=torch.long) for i, k in enumerate(keep)])
        weights = torch.full((n,), 1.0 / n, dtype=torch.float64)
        acceptance = [a for r in runs for a in r.acceptance]
        stats = {"method": "smc", "runs": len(runs), "particles": m, "reference_components": int(q.means.shape[0]),
                 "stages": max(r.stages for r in runs), "moves": sum(r.moves for r in runs),
                 "mean_acceptance": sum(acceptance) / max(len(acceptance), 1),
                 "final_acceptance": runs[-1].acceptance[-1] if runs[-1].acceptance else None,
                 "first_step_ess": runs[0].ess_steps[0] if runs[0].ess_steps else None,
                 "log_evidence": [r.log_z for r in runs],
                 "unique_samples": int(torch.unique(x, dim=0).shape[0]),
                 "rollouts": post.rollouts - rollouts0 + sum(c.rollouts for c in chain),
                 "rollouts_by_length": post.rollouts - rollouts0
                 + sum(c.rollouts * c.problem.steps / post.problem.steps for c in chain),
                 "seconds": time.perf_counter() - t0}
        nearest_mode = torch.cdist(x, q.means).argmin(-1)  # in scaled parameters
        return PosteriorSamples(x=x, weights=weights, log_density=lp, component=nearest_mode, run=run,
                                mode_index=mode_index, stats=stats)
