"""Model uncertainty in the likelihood: the observed end averaged over physics variants.

A real end comes from the real world, not from this simulator: friction,
restitution and the penalty contact's stiffness are known only roughly. With
``<model-uncertainty friction restitution>`` (relative standard deviations)
the likelihood of an end is averaged over K variants of the physics drawn
around the scene's values, and the search prefers pasts whose end holds up
under them over "needle" pasts whose end hinges on the exact contact.

The average is of the log-likelihood (``Posterior``'s least squares): the
observation residuals r_k of every variant, each scaled by ``1 / sqrt(K)``,
are stacked, so

    0.5 |R|^2 = 0.5 (1/K) sum_k |r_k|^2 = 0.5 |mean_k r_k|^2 + 0.5 (1/K) sum_k |r_k - mean r|^2,

the misfit of the variants' mean end plus their spread: a past whose end
moves by centimetres when the friction changes by 10 % pays for it. (The log of
the averaged likelihood would instead reward the one variant that fits; it is
also no sum of squares, which the Levenberg-Marquardt stage needs.)

Common random numbers: the variants are fixed for a solve (a deterministic
design, or seeded draws), so every candidate is judged under the same
physics and the objective stays a smooth function of the start, with exact
Jacobians (each variant's rollout carries its own). The default K = 4 is the
two-level orthogonal design of three factors in four runs (friction,
restitution, stiffness at -1 or +1 standard deviation, each level twice, every
pair of factors balanced): it reproduces each factor's mean and variance
exactly, which is what a quadratic expansion of the log-likelihood needs.
Other K draw standard normals (seeded) and standardise each factor.

Ranking on held-out variants: Levenberg-Marquardt fits each mode to the
K variants it is refined on, and where the end hinges on the contacts (a box
tumbling over its edges) a 12-parameter start can fit four fixed physics at
once by chance: a winner's curse, the fitted cost is the best of many
tries, not what the physics' uncertainty leaves of it. So the refined modes
are ranked by their negative log posterior under ``ModelParams.heldout_variants`` other
variants, drawn (seeded, standardised) at the same standard deviations, that
no mode was fitted to: an estimate of the averaged likelihood free of that
selection bias. It costs H rollouts per mode, no Jacobians. Measured on the
cross-engine benchmark's tumbling boxes (docs/physics-fidelity.md, "Model
uncertainty: modes ranked on held-out variants").

Engines: the native engine and the torch reference read friction,
restitution and stiffness from the ``World`` (one value per body-static and
body-body pair), not per batch element, so the K variants are K Worlds
(``dataclasses.replace``: cheap, and each is packed once) and a batch of B
candidates costs K rollouts of B.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from dejaview.errors import InferenceError
from dejaview.inference.params import ModelParams

DESIGN4 = ((1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0))
"""The 2^(3-1) design: (friction, restitution, stiffness) levels in standard deviations."""


def design(count: int, seed: int = 0) -> torch.Tensor:
    """(K, 3) standard-normal levels of (friction, restitution, stiffness), fixed per solve."""
    if count == 4:
        return torch.tensor(DESIGN4, dtype=torch.float64)
    if count < 2:
        raise InferenceError(f"model uncertainty needs at least 2 variants, got {count}")
    z = torch.randn(count, 3, generator=torch.Generator().manual_seed(int(seed)), dtype=torch.float64)
    return (z - z.mean(0)) / z.std(0, unbiased=False)


@dataclass(frozen=True)
class ModelVariants:
    """K physics variants of one World.

    Attributes:
        friction, restitution, stiffness: relative standard deviations.
        levels: (K, 3) levels in standard deviations.
        worlds: the K variant Worlds.
    """

    friction: float
    restitution: float
    stiffness: float
    levels: torch.Tensor
    worlds: tuple

    @property
    def count(self) -> int:
        return len(self.worlds)

    @staticmethod
    def from_world(world, friction: float = 0.0, restitution: float = 0.0,
                   stiffness: float = ModelParams.stiffness_sd, count: int = ModelParams.variants,
                   seed: int = 0) -> "ModelVariants":
        """Variants of ``world``: each pair's friction times ``1 + friction z_f``, restitution times
        ``1 + restitution z_e`` (clipped to [0, 1]), contact frequency times ``sqrt(1 + stiffness
        z_k)`` (the stiffness is m omega_0^2), for the design's levels z."""
        for name, v in (("friction", friction), ("restitution", restitution), ("stiffness", stiffness)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise InferenceError(f"model uncertainty: {name} must be a number >= 0, got {v!r}")
        levels = design(int(count), seed)
        worlds = tuple(vary_world(world, 1.0 + friction * float(z[0]), 1.0 + restitution * float(z[1]),
                                  1.0 + stiffness * float(z[2])) for z in levels)
        return ModelVariants(float(friction), float(restitution), float(stiffness), levels, worlds)

    def heldout(self, world, seed: int = 0, count: int = ModelParams.heldout_variants) -> "ModelVariants":
        """``count`` variants of ``world`` (the scene's physics) at these standard deviations, drawn
        from another stream than this design's (``ModelParams.heldout_seed + seed``)."""
        return ModelVariants.from_world(world, self.friction, self.restitution, self.stiffness,
                                        count=count, seed=ModelParams.heldout_seed + int(seed))

    @staticmethod
    def from_scene(scene, world, count: int = ModelParams.variants) -> "ModelVariants | None":
        """The scene's ``<model-uncertainty>`` as variants of ``world``; None where absent or zero."""
        mu = scene.inference.model_uncertainty if scene.inference is not None else None
        if mu is None or not ((mu.friction or 0.0) > 0 or (mu.restitution or 0.0) > 0):
            return None
        return ModelVariants.from_world(world, mu.friction or 0.0, mu.restitution or 0.0,
                                        count=count, seed=scene.inference.seed)

    def to_json(self) -> dict:
        """``result.json``'s ``model_uncertainty``."""
        return {"friction": self.friction, "restitution": self.restitution, "stiffness": self.stiffness,
                "variants": self.count, "levels": self.levels.tolist(),
                "likelihood": "mean over the variants of the Gaussian log-likelihood"}

    def trajectories(self, problem, x: torch.Tensor, checkpoint: bool = False) -> list:
        """The K rollouts (one per variant World) of parameters x (B, P)."""
        return [replace(problem, world=w).simulate(x, checkpoint=checkpoint) for w in self.worlds]


def vary_world(world, friction_factor: float, restitution_factor: float, stiffness_factor: float):
    """``world`` with every friction, restitution and the contact stiffness scaled.

    Restitution is recovered from each pair's unloading factor (``World.restitution_to_unloading``
    inverted), scaled, clipped to [0, 1] and mapped back at the new stiffness, so a variant's
    impacts rebound with the scaled restitution.
    """
    from dejaview.sim.world import remap_unloading

    f = max(friction_factor, ModelParams.min_factor)
    k = max(stiffness_factor, ModelParams.min_factor)
    h = world.dt / world.substeps
    omega = world.contact.frequency * math.sqrt(k)
    omega_h0, omega_h = world.contact.frequency * h, omega * h

    def unload(phi: torch.Tensor) -> torch.Tensor:
        return remap_unloading(phi, omega_h0, omega_h, restitution_factor)

    return replace(world, mu_static=world.mu_static * f, mu_pair=world.mu_pair * f,
                   unload_static=unload(world.unload_static), unload_pair=unload(world.unload_pair),
                   contact=replace(world.contact, frequency=omega))


def rank_on_heldout(post, modes: list, seed: int = 0) -> tuple[list, int]:
    """``modes`` ranked by their negative log posterior under held-out physics variants.

    Args:
        post: ``Posterior`` with ``model`` set (the variants the modes were refined on).
        modes: refined ``Mode``s (x (P,), cost on ``post``).
        seed: the solve's seed (the held-out draws: ``ModelVariants.heldout``).
    Returns:
        (the modes with ``heldout`` (their cost) and ``heldout_mean_chi2`` (the observation chi-square
        of the held-out variants' mean residual: their mean end's misfit) set, lowest cost first (a
        mode whose held-out cost is not finite last), the candidates evaluated
        (``Posterior.rollouts``' count: each under every held-out variant)). One mode or none is
        returned as it is, with 0.
    """
    if len(modes) < 2:
        return list(modes), 0
    held = post.with_model(post.model.heldout(post.problem.world, seed))
    x = torch.stack([m.x for m in modes]).to(torch.float64)
    with torch.no_grad():
        trajs = held.trajectories(x)
        mean = torch.stack([held.observation_residuals(t)[0] for t in trajs]).mean(0)  # (B, n)
    held.rollouts += x.shape[0]
    cost = held.cost(x, trajs=trajs)[0]
    chi2 = torch.where(torch.isfinite(cost), (mean * mean).sum(-1), torch.full_like(cost, math.inf))
    ranked = [replace(m, heldout=float(c), heldout_mean_chi2=float(q))
              for m, c, q in zip(modes, cost.tolist(), chi2.tolist())]
    ranked.sort(key=lambda m: m.heldout if math.isfinite(m.heldout) else math.inf)
    return ranked, held.rollouts


def explains_end(post, mode) -> bool:
    """Whether ``mode``'s end fits the observation under the physics' uncertainty: the end its
    held-out variants reach on average (``rank_on_heldout``'s ``heldout_mean_chi2``) within the
    observation's noise, its chi-square at most the ``1 - ModelParams.unexplained_p`` quantile of a chi-square
    with ``post.num_observed`` degrees of freedom. The variants' spread about that mean is left
    out: the physics' uncertainty spreads every past's end, the truth's too, and a needle's mean
    end is off where its variants fall the other way. A mode never ranked counts as explaining
    (there was nothing to rank it against)."""
    from scipy.stats import chi2

    if mode.heldout_mean_chi2 is None:
        return True
    return mode.heldout_mean_chi2 <= float(chi2.ppf(1.0 - ModelParams.unexplained_p, max(1, post.num_observed)))
