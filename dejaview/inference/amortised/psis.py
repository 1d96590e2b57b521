"""Pareto-smoothed importance sampling (Vehtari, Simpson, Gelman, Yao and Gabry 2024).

``psis(log_w)`` smooths the largest importance weights by the quantiles of a generalised Pareto
distribution fitted to them (Zhang and Stephens 2009, with Vehtari et al.'s weakly informative
prior on the shape), truncated at the largest raw weight, and returns the shape estimate k-hat:
below 0.7 the weighted estimates are reliable (their error falls as the draws grow); above it the
proposal misses where the target's mass is and no number of draws will do. The same algorithm as
ArviZ's ``psislw`` (which is not a dependency of the core package).
"""

from __future__ import annotations

import math

import numpy as np
import torch


def psis(log_w: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Smoothed normalised log weights (S,) and k-hat of raw log weights ``log_w`` (S,) (``-inf``
    for a draw of density 0). k-hat is ``inf`` with fewer than 5 finite draws in the tail."""
    lw = log_w.detach().to(torch.float64).cpu().numpy().copy()
    finite = np.isfinite(lw)
    if not finite.any():
        return torch.full_like(log_w, -math.inf, dtype=torch.float64), math.inf
    lw[~finite] = -np.inf
    lw -= lw[finite].max()
    s = int(finite.sum())
    tail_len = int(math.ceil(min(0.2 * s, 3 * math.sqrt(s))))
    order = np.argsort(lw)
    k = math.inf
    if tail_len >= 5 and s > tail_len + 1:
        cutoff = max(lw[order[-tail_len - 1]], math.log(np.finfo(float).tiny))
        tail = order[-tail_len:]
        tail = tail[lw[tail] > cutoff]
        if tail.size >= 5:
            exceed = np.exp(lw[tail]) - math.exp(cutoff)
            k, sigma = _gpd_fit(exceed)
            if math.isfinite(k) and sigma > 0:
                probs = (np.arange(tail.size) + 0.5) / tail.size
                smoothed = np.log(_gpd_quantile(probs, k, sigma) + math.exp(cutoff))
                lw[tail] = np.minimum(smoothed, 0.0)  # sorted ascending, as ``tail`` is
    lw[finite] -= np.logaddexp.reduce(lw[finite])
    return torch.as_tensor(lw, dtype=torch.float64), float(k)


def _gpd_fit(x: np.ndarray) -> tuple[float, float]:
    """Shape k and scale sigma of a generalised Pareto distribution fitted to exceedances x
    (ascending, positive): Zhang and Stephens' posterior-mean estimate, k shrunk towards 0.5 by a
    prior worth 10 draws."""
    n = x.size
    m = 30 + int(math.sqrt(n))
    b = 1 - np.sqrt(m / (np.arange(1, m + 1) - 0.5))
    b /= 3 * x[int(n / 4 + 0.5) - 1]
    b += 1 / x[-1]
    k = np.log1p(-b[:, None] * x).mean(axis=1)
    length = n * (np.log(-(b / k)) - k - 1)
    weights = 1 / np.exp(length - length[:, None]).sum(axis=1)
    keep = weights >= 10 * np.finfo(float).eps
    weights, b = weights[keep], b[keep]
    weights /= weights.sum()
    b_post = float((b * weights).sum())
    k_post = float(np.log1p(-b_post * x).mean())
    sigma = -k_post / b_post
    k_post = (n * k_post + 10 * 0.5) / (n + 10)
    return k_post, sigma


def _gpd_quantile(p: np.ndarray, k: float, sigma: float) -> np.ndarray:
    """Quantiles at probabilities p of the generalised Pareto distribution (shape k, scale sigma)."""
    if abs(k) < np.finfo(float).eps:
        return -sigma * np.log1p(-p)
    return sigma * np.expm1(-k * np.log1p(-p)) / k


__all__ = ["psis"]
