"""The sampler's densities: the prior, the target, and the reference mixture at the search's modes.

- ``prior_draws`` / ``log_prior_density``: the stated prior (``<prior>``, the
  start area) as draws and as a normalised density over the free parameters x.
- ``log_density``: the target, ``-0.5 |R(x)|^2`` (``Posterior``'s residuals) plus
  the log density of the parameterisation's base measure (``log_base_density``):
  the start position is uniform in the start area, which in the layout's logit
  coordinates is the logistic density; an orientation without ``<prior tilt>``
  is uniform on SO(3), which in rotation-vector coordinates has density
  ``(1 - cos t) / t^2`` for angles t up to pi. Infeasible starts
  (``Posterior.feasible``) and non-finite rollouts have density 0.
- ``Mixture`` / ``laplace_mixture``: the reference q of ``dejaview.inference.sampling``,
  multivariate Student-t components at the search's distinct modes with their
  Laplace covariances (exact residual Jacobians), weighted by Laplace evidence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dejaview.errors import InferenceError
from dejaview.inference.params import SamplerParams


def prior_draws(post, n: int, gen: torch.Generator) -> torch.Tensor:
    """n draws (n, P) from the prior of ``log_prior_density``: position uniform in the start
    area (logistic in its logit coordinates), orientation normal with ``tilt`` or Haar-uniform,
    velocities normal with ``speed`` / ``spin`` or uniform in the ball of their flat bound."""
    lay, s = post.layout, post.settings
    dt = torch.float64
    parts = []
    cols = lay.block_slice("position")
    if cols.stop > cols.start:
        u = torch.rand(n, cols.stop - cols.start, generator=gen, dtype=dt).clamp(1e-9, 1 - 1e-9)
        parts.append(torch.logit(u) if lay.lo is not None else 2 * u - 1)
    if lay.free["orientation"]:
        if s.tilt is not None:
            r = s.tilt * torch.randn(n, 3, generator=gen, dtype=dt)
        else:  # uniform rotation (a random unit quaternion) as a rotation vector of angle <= pi
            q = torch.randn(n, 4, generator=gen, dtype=dt)
            q = q / q.norm(dim=-1, keepdim=True)
            q = torch.where(q[:, :1] < 0, -q, q)
            angle = 2 * torch.atan2(q[:, 1:].norm(dim=-1), q[:, 0])
            axis = q[:, 1:] / q[:, 1:].norm(dim=-1, keepdim=True).clamp_min(1e-300)
            r = axis * angle[:, None]
        parts.append(r / lay.scale["orientation"])
    for block, sd, bound in (("linear_velocity", s.speed, s.speed_bound),
                             ("angular_velocity", s.spin, s.spin_bound)):
        cols = lay.block_slice(block)
        w = cols.stop - cols.start
        if w:
            if sd is not None:
                v = sd * torch.randn(n, w, generator=gen, dtype=dt)
            else:
                d = torch.randn(n, w, generator=gen, dtype=dt)
                d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-300)
                v = d * bound * torch.rand(n, 1, generator=gen, dtype=dt) ** (1 / 3)
            parts.append(v / lay.scale[block])
    cols = lay.block_slice("physics")
    if cols.stop > cols.start:  # standard normals (dejaview.sim.physics)
        parts.append(torch.randn(n, cols.stop - cols.start, generator=gen, dtype=dt))
    return torch.cat(parts, -1)


def log_prior_density(post, x: torch.Tensor) -> torch.Tensor:
    """Normalised log density (B,) of ``prior_draws`` at x (B, P) (``-inf`` outside a flat
    velocity bound or beyond an orientation angle of pi)."""
    lay, s = post.layout, post.settings
    out = log_base_density(post, x)
    cols = lay.block_slice("orientation")
    if cols.stop > cols.start:
        sc = lay.scale["orientation"]
        if s.tilt is not None:
            r = sc * x[:, cols]
            out = out - 0.5 * (r * r).sum(-1) / s.tilt ** 2 - 3 * math.log(s.tilt * math.sqrt(2 * math.pi))
        else:  # Haar: (1 - cos t) / (t^2 4 pi^2) per unit volume of rotation vectors
            out = out - math.log(4 * math.pi ** 2)
        out = out + 3 * math.log(sc)
    for block, sd, bound in (("linear_velocity", s.speed, s.speed_bound),
                             ("angular_velocity", s.spin, s.spin_bound)):
        cols = lay.block_slice(block)
        if cols.stop > cols.start:
            sc = lay.scale[block]
            v = sc * x[:, cols]
            w = cols.stop - cols.start
            if sd is not None:
                out = out - 0.5 * (v * v).sum(-1) / sd ** 2 - w * math.log(sd * math.sqrt(2 * math.pi))
            else:  # uniform in the ball of radius ``bound`` (w = 3)
                inside = v.norm(dim=-1) <= bound
                out = torch.where(inside, out - math.log(4 / 3 * math.pi * bound ** 3),
                                  torch.full_like(out, -math.inf))
            out = out + w * math.log(sc)
    z = x[:, lay.block_slice("physics")]
    if z.shape[1]:
        out = out - 0.5 * (z * z).sum(-1) - z.shape[1] * 0.5 * math.log(2 * math.pi)
    return out


def log_base_density(post, x: torch.Tensor) -> torch.Tensor:
    """Log density (B,) of the prior's base measure at parameters x (B, P), up to a constant
    (module docstring): logistic for positions in a start area, Haar for a flat orientation
    (``-inf`` beyond an angle of pi), 0 for the rest. The normal priors and the flat priors'
    soft bounds are residuals of ``Posterior.prior_residuals``."""
    lay = post.layout
    out = torch.zeros(x.shape[0], dtype=x.dtype)
    cols = lay.block_slice("position")
    if cols.stop > cols.start and lay.lo is not None:
        u = x[:, cols]
        out = out - (torch.nn.functional.softplus(u) + torch.nn.functional.softplus(-u)).sum(-1)
    cols = lay.block_slice("orientation")
    if cols.stop > cols.start and post.settings.tilt is None:
        t = lay.scale["orientation"] * x[:, cols].norm(dim=-1)
        out = out + torch.where(t <= math.pi, log_haar(t), torch.full_like(t, -math.inf))
    return out


def log_haar(angle: torch.Tensor) -> torch.Tensor:
    """log of ``(1 - cos t) / t^2`` (B,) at rotation angles t (B,): the Haar measure's density in
    rotation-vector coordinates, up to a constant (series below 1e-4)."""
    haar = torch.where(angle < 1e-4, torch.full_like(angle, 0.5) - angle * angle / 24,
                       (1 - torch.cos(angle)) / (angle * angle).clamp_min(1e-300))
    return torch.log(haar.clamp_min(1e-300))


def log_density(post, x: torch.Tensor, feasibility: bool = True, trajs: list | None = None) -> torch.Tensor:
    """Unnormalised log posterior density (B,) of parameters x (B, P): ``-cost + log base``,
    ``-inf`` where the start is infeasible or the rollout not finite (simulates B candidates,
    unless their rollouts ``trajs`` are given: ``Posterior.trajectories``).
    ``feasibility=False``: as if every start were feasible (the caller checks those it keeps)."""
    cost, _, _ = post.cost(x, feasibility=feasibility, trajs=trajs)
    out = -cost + log_base_density(post, x)
    return torch.where(torch.isfinite(out), out, torch.full_like(out, -math.inf))


def _base_curvature(post, x: torch.Tensor) -> torch.Tensor:
    """Diagonal (P,) added to J^T J at a mode x (P,): the curvature of ``-log_base_density``
    and, for a flat velocity prior, one over the square of its bound (so the reference spreads
    over the prior's range where the observation leaves a direction free)."""
    lay, s = post.layout, post.settings
    c = torch.zeros(lay.size, dtype=x.dtype)
    cols = lay.block_slice("position")
    if cols.stop > cols.start:
        if lay.lo is not None:
            sig = torch.sigmoid(x[cols])
            c[cols] = 2 * sig * (1 - sig)
        else:
            c[cols] = 1e-4
    cols = lay.block_slice("orientation")
    if cols.stop > cols.start and s.tilt is None:
        c[cols] = lay.scale["orientation"] ** 2 / 6 + (lay.scale["orientation"] / math.pi) ** 2
    for block, sd, bound in (("linear_velocity", s.speed, s.speed_bound),
                             ("angular_velocity", s.spin, s.spin_bound)):
        cols = lay.block_slice(block)
        if cols.stop > cols.start and sd is None:
            c[cols] = (lay.scale[block] / bound) ** 2
    return c


@dataclass
class Mixture:
    """A mixture of multivariate Student-t distributions over x (P,).

    Attributes:
        means: (K, P); chol: (K, P, P) lower Cholesky factors of the scale matrices;
        log_weights: (K,) normalised; df: degrees of freedom.
    """

    means: torch.Tensor
    chol: torch.Tensor
    log_weights: torch.Tensor
    df: float = SamplerParams.reference_df
    prior: object = None
    """Optional ``Posterior`` whose prior (``prior_draws``, ``log_prior_density``) is one more
    component, with weight ``prior_share``; the t components share the rest."""
    prior_share: float = 0.0
    flow: object = None
    """Optional proposal with ``sample(n, gen)`` and ``log_prob(x)`` (an amortised posterior at the
    observation, ``dejaview.inference.amortised.answer.FlowProposal``): one more component, last,
    with weight ``flow_share`` of the whole."""
    flow_share: float = 0.0

    def sample(self, n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """n draws (n, P) and the component (n,) each came from (K for the prior, then the flow)."""
        x, k = self._sample_t(n, gen)
        if self.prior is not None and self.prior_share > 0:
            use = torch.rand(n, generator=gen, dtype=torch.float64) < self.prior_share
            m = int(use.sum())
            if m:
                x[use] = prior_draws(self.prior, m, gen)
                k[use] = self.means.shape[0]
        if self.flow is not None and self.flow_share > 0:
            use = torch.rand(n, generator=gen, dtype=torch.float64) < self.flow_share
            m = int(use.sum())
            if m:
                x[use] = self.flow.sample(m, gen).to(x.dtype)
                k[use] = self.means.shape[0] + (self.prior is not None and self.prior_share > 0)
        return x, k

    def _sample_t(self, n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        k = torch.multinomial(self.log_weights.exp(), n, replacement=True, generator=gen)
        p = self.means.shape[1]
        z = torch.randn(n, p, generator=gen, dtype=self.means.dtype)
        chi2 = 2 * torch._standard_gamma(torch.full((n,), self.df / 2, dtype=self.means.dtype), generator=gen)
        scale = torch.sqrt(self.df / chi2.clamp_min(1e-300))
        x = self.means[k] + scale[:, None] * (self.chol[k] @ z.unsqueeze(-1)).squeeze(-1)
        return x, k

    def component_log_prob(self, x: torch.Tensor) -> torch.Tensor:
        """(B, K), plus a column for the prior and one for the flow where they are components: log
        density of each component (weights included) at x (B, P)."""
        p = self.means.shape[1]
        d = x[:, None, :] - self.means[None]  # (B, K, P)
        sol = torch.linalg.solve_triangular(self.chol[None].expand(x.shape[0], -1, -1, -1),
                                            d.unsqueeze(-1), upper=False).squeeze(-1)
        m = (sol * sol).sum(-1)  # (B, K) squared Mahalanobis distances
        logdet = torch.log(torch.diagonal(self.chol, dim1=-2, dim2=-1)).sum(-1)  # (K,)
        nu = self.df
        c = (math.lgamma((nu + p) / 2) - math.lgamma(nu / 2) - 0.5 * p * math.log(nu * math.pi))
        out = self.log_weights + c - logdet - 0.5 * (nu + p) * torch.log1p(m / nu)
        if self.prior is not None and self.prior_share > 0:
            lp = math.log(self.prior_share) + log_prior_density(self.prior, x)
            out = torch.cat([out + math.log1p(-self.prior_share), lp[:, None]], -1)
        if self.flow is not None and self.flow_share > 0:
            lf = math.log(self.flow_share) + self.flow.log_prob(x)
            out = torch.cat([out + math.log1p(-self.flow_share), lf[:, None]], -1)
        return out

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) log density at x (B, P)."""
        return torch.logsumexp(self.component_log_prob(x), -1)

    def component(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) the most responsible component at x (B, P)."""
        return self.component_log_prob(x).argmax(-1)


def laplace_mixture(post, modes: list, params: SamplerParams | None = None) -> tuple[Mixture, list[int]]:
    """The reference mixture q of the module docstring at the search's modes.

    Args:
        post: ``Posterior``; modes: the search's ``Mode`` list (x (P,), cost), best first.
        params: ``SamplerParams`` (``reference_df``, ``scale_inflation``, ``mode_merge``).
    Returns:
        the mixture and, per component, the index of the mode it came from.
    """
    params = SamplerParams() if params is None else params
    finite = [i for i, m in enumerate(modes) if math.isfinite(m.cost)]
    if not finite:
        raise InferenceError("no mode with a finite posterior density to sample around")
    xs = torch.stack([modes[i].x.to(torch.float64) for i in finite])
    r, J = post.jacobian(xs)
    p = xs.shape[1]
    covs, logp, kept, means = [], [], [], []
    lp = -0.5 * (r * r).sum(-1) + log_base_density(post, xs)
    for i in range(xs.shape[0]):
        H = J[i].T @ J[i] + torch.diag(_base_curvature(post, xs[i]))
        H = 0.5 * (H + H.T) + 1e-9 * torch.eye(p, dtype=H.dtype) * float(torch.diagonal(H).mean().clamp_min(1e-12))
        cov = torch.linalg.inv(H)
        cov = 0.5 * (cov + cov.T)
        dup = False
        for j, mj in enumerate(means):
            d = xs[i] - mj
            if float(d @ torch.linalg.solve(covs[j], d)) < params.mode_merge ** 2:
                dup = True
                break
        if dup or not bool(torch.isfinite(lp[i])):
            continue
        means.append(xs[i])
        covs.append(cov)
        logp.append(float(lp[i]))
        kept.append(finite[i])
    chol = torch.linalg.cholesky(torch.stack(covs)) * params.scale_inflation
    logdet = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    lw = torch.tensor(logp, dtype=torch.float64) + logdet  # Laplace evidence
    return Mixture(torch.stack(means), chol, lw - torch.logsumexp(lw, 0), df=params.reference_df), kept
