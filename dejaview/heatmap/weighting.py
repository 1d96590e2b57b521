"""From the solutions found in each cell to cell probabilities.

Three steps, each a plain function of tensors so tests can pin them:

1. ``deduplicate``: within one cell, solutions that describe the same start
   (initial linear velocity within ``velocity_tol`` m/s, angular velocity
   within ``spin_tol`` rad/s, start position within ``position_tol`` m and
   orientation within ``angle_tol`` radians) are one solution found several
   times; the one with the lowest loss is kept, so a solution found by every
   sample of a cell counts once.
2. ``robustness_levels``: how wide the basin of a solution is. Its initial
   velocity is perturbed by growing radii rho_1 < ... < rho_R (m/s; the
   angular velocity, where free, by ``spin_per_speed`` * rho rad/s along the
   same random direction) in D random directions each. The basin holds at
   radius rho_k when at least half of the D perturbed starts keep their loss
   at or below ``loss + sigma`` (they still explain the observation within
   the simulation-error scale). The level n is the number of consecutive radii,
   from the smallest, at which the basin holds (0..R).
3. ``cell_probability``: each kept solution s with loss l_s and level n_s
   weighs

       w_s = exp(-l_s^2 / (2 sigma^2)) * (1 + n_s) / (1 + R)

   the likelihood of its loss under a normal distribution around zero with
   scale sigma (its constant factor cancels), refined by the robustness: a
   basin that holds at every radius weighs 1 + R times one that breaks at
   the smallest. A cell's probability is the sum of its solutions' weights,
   normalised over all cells (in log space, so a scene where every loss is
   many sigma away still gives a distribution: the least bad cells).
"""

from __future__ import annotations

import math

import torch


def deduplicate(cell: torch.Tensor, loss: torch.Tensor, start: dict[str, torch.Tensor], *,
                velocity_tol: float = 0.05, spin_tol: float = 0.5, position_tol: float = 0.02,
                angle_tol: float = math.radians(10.0)) -> torch.Tensor:
    """Indices of the solutions kept after removing near-duplicates within each cell.

    Args:
        cell: (K,) cell index of every solution.
        loss: (K,) losses (non-finite ones are dropped).
        start: initial states, ``position`` (K, 3), ``orientation`` (K, 4),
            ``linear_velocity`` (K, 3), ``angular_velocity`` (K, 3).
        velocity_tol, spin_tol, position_tol, angle_tol: what counts as the same start.
    Returns:
        (M,) indices into the K solutions, sorted by cell then loss.
    """
    from dejaview.sim.rotation import geodesic_angle

    finite = torch.isfinite(loss)
    order = sorted((i for i in range(len(loss)) if bool(finite[i])),
                   key=lambda i: (int(cell[i]), float(loss[i])))
    kept: list[int] = []
    by_cell: dict[int, list[int]] = {}
    for i in order:
        c = int(cell[i])
        same = False
        for j in by_cell.get(c, []):
            dv = float((start["linear_velocity"][i] - start["linear_velocity"][j]).norm())
            dw = float((start["angular_velocity"][i] - start["angular_velocity"][j]).norm())
            dp = float((start["position"][i] - start["position"][j]).norm())
            da = float(geodesic_angle(start["orientation"][i], start["orientation"][j]))
            if dv <= velocity_tol and dw <= spin_tol and dp <= position_tol and da <= angle_tol:
                same = True
                break
        if not same:
            by_cell.setdefault(c, []).append(i)
            kept.append(i)
    return torch.tensor(kept, dtype=torch.long)


def perturbation_directions(n: int, directions: int, spin: bool, generator: torch.Generator,
                            dtype=torch.float64) -> torch.Tensor:
    """Random unit directions (n, D, 6) in (linear, angular) velocity space.

    The angular half is zero unless ``spin``; each direction has unit norm over
    the perturbed components.
    """
    dims = 6 if spin else 3
    d = torch.randn(n, directions, dims, generator=generator, dtype=dtype)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if not spin:
        d = torch.cat([d, torch.zeros_like(d)], -1)
    return d


def robustness_levels(loss: torch.Tensor, perturbed_loss: torch.Tensor, sigma: float) -> torch.Tensor:
    """Basin level of each solution from the losses of its perturbed starts.

    Args:
        loss: (M,) losses of the solutions.
        perturbed_loss: (M, R, D) losses after perturbing by radius k (ascending) in direction d.
        sigma: the simulation-error scale (loss units).
    Returns:
        (M,) long: number of consecutive radii, from the smallest, at which at least
        half of the directions keep the loss at or below ``loss + sigma``.
    """
    low = perturbed_loss <= (loss[:, None, None] + sigma)
    low = low & torch.isfinite(perturbed_loss)
    holds = low.double().mean(-1) >= 0.5  # (M, R)
    return torch.cumprod(holds.long(), dim=-1).sum(-1)


def log_weights(loss: torch.Tensor, level: torch.Tensor, radii: int, sigma: float) -> torch.Tensor:
    """log w_s = -l^2 / (2 sigma^2) + log((1 + n) / (1 + R)) for losses (M,) and levels (M,)."""
    return -(loss * loss) / (2.0 * sigma * sigma) + torch.log((1.0 + level.to(loss.dtype)) / (1.0 + radii))


def cell_probability(cell: torch.Tensor, logw: torch.Tensor, num_cells: int) -> torch.Tensor:
    """(C,) normalised probability of each cell from the log weights (M,) of its solutions.

    Cells without a kept solution get 0.
    """
    if logw.numel() == 0:
        raise ValueError("no solution to weigh")
    w = torch.exp(logw - logw.max())
    p = torch.zeros(num_cells, dtype=logw.dtype).index_add_(0, cell, w)
    return p / p.sum()


def entropy_bits(p: torch.Tensor) -> float:
    """Shannon entropy (bits) of a probability vector; uniform over C cells gives log2(C)."""
    q = p[p > 0]
    return float(-(q * torch.log2(q)).sum())
