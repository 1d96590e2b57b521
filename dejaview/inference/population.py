"""A weighted particle population's arithmetic, for ``dejaview.inference.sampling``'s moves:
its effective sample size, systematic resampling, the Cholesky factor of its covariance,
differential-evolution steps between its members, a walk's step-scale adaptation, and the walk's
coordinates (a start-area position as its fraction of the area)."""

from __future__ import annotations

import math

import torch


def ess(logw: torch.Tensor) -> float:
    """Effective sample size of log weights logw (N,)."""
    w = torch.softmax(logw, 0)
    return float(1.0 / (w * w).sum())


def chol_of(points: torch.Tensor) -> torch.Tensor:
    """(P, P) Cholesky factor of the covariance of points (M, P) (the identity for one point; the
    diagonal's roots where the covariance is singular)."""
    p = points.shape[1]
    eye = torch.eye(p, dtype=points.dtype)
    c = torch.cov(points.T).reshape(p, p) if points.shape[0] > 1 else eye.clone()
    c = c + 1e-9 * eye * float(torch.diagonal(c).mean().clamp_min(1e-12))
    chol, info = torch.linalg.cholesky_ex(c)
    return chol if int(info) == 0 else torch.diag(torch.sqrt(torch.diagonal(c).clamp_min(1e-12)))


def difference_steps(population: torch.Tensor, r: int, gen: torch.Generator
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """r differential-evolution steps ``g (w_a - w_b)`` (r, P) between distinct members a, b of
    ``population`` (M >= 2, P), and their jitters e (r, P) (``sampling._SMC.difference_move``)."""
    m, p = population.shape
    a = torch.randint(m, (r,), generator=gen)
    b = (a + torch.randint(1, m, (r,), generator=gen)) % m  # never a
    jitter = 1e-4 * population.std(0).clamp_min(1e-12)
    e = jitter * torch.randn((r, p), generator=gen, dtype=torch.float64)
    return 2.38 / math.sqrt(2 * p) * (population[a] - population[b]), e


def adapted(scale: float, acceptance: float, target: float) -> float:
    """A walk's step scale moved towards the acceptance rate ``target`` after a move accepting
    ``acceptance``."""
    return float(min(max(scale * math.exp(acceptance - target), 1e-3), 3.0))


def systematic(logw: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Systematic resampling: (N,) indices."""
    n = logw.shape[0]
    w = torch.softmax(logw, 0)
    u = (torch.rand(1, generator=gen, dtype=w.dtype) + torch.arange(n, dtype=w.dtype)) / n
    return torch.searchsorted(torch.cumsum(w, 0), u).clamp_max(n - 1)


def to_walk(layout, x: torch.Tensor) -> torch.Tensor:
    """The walk's coordinates (B, P) of parameters x (B, P) under ``layout`` (a ``ParameterLayout``):
    a position inside a start area as its fraction of the area, ``sigmoid(u)`` in (0, 1), the rest
    as they are.

    Why: an end that leaves the position free spreads its posterior evenly over the start
    area, which the layout's logit coordinates turn into the logistic density, whose tails
    hold a quarter of the mass beyond |u| = 2 and thin out where the population's steps
    are short; in fractions the same posterior is flat between walls."""
    cols = layout.block_slice("position")
    if cols.stop == cols.start or layout.lo is None:
        return x
    w = x.clone()
    w[:, cols] = torch.sigmoid(x[:, cols])
    return w


def from_walk(layout, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Parameters x (B, P) at walk coordinates w (B, P) (``to_walk``), and ``log |dx/dw|`` (B,) there
    (``-inf`` outside the start area: a fraction beyond (0, 1))."""
    cols = layout.block_slice("position")
    if cols.stop == cols.start or layout.lo is None:
        return w, torch.zeros(w.shape[0], dtype=w.dtype)
    f = w[:, cols]
    inside = ((f > 0) & (f < 1)).all(-1)
    f = torch.where(inside[:, None], f, torch.full_like(f, 0.5))
    x = w.clone()
    x[:, cols] = torch.logit(f)
    log_jac = -(torch.log(f) + torch.log1p(-f)).sum(-1)
    return x, torch.where(inside, log_jac, torch.full_like(log_jac, -math.inf))
