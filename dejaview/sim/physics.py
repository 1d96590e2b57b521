"""Physics not known exactly: friction, restitution and stiffness as unknowns beside the start.

``<physics-prior friction restitution stiffness>`` gives relative standard deviations s of
log-normal priors around the scene's values. Each inferred parameter is a standard normal z
(the parameter vector's ``physics`` block, ``dejaview.backends.params``), and

    friction factor    f_mu = exp(s_f z_f)              on every pair's friction coefficient,
    restitution        e    = min(1, e0 exp(s_e z_e))   e0 the scene's (``<simulation restitution>``),
    stiffness factor   f_k  = exp(s_k z_k)              on the contact stiffness k = m omega_0^2.

Per-object overrides of friction and restitution stay where the scene puts them relative to the
scene's value: the factors apply to every pair alike.

The engines take one physics per candidate as the logs of three factors (``World.physics``,
``rollout(physics=...)``): on friction, on the unloading factor phi of the hysteretic contact
above its least m = ``UNLOAD_MIN`` (``dejaview.sim.contacts``; phi' = m + f (phi - m), capped at
1) and on the stiffness. A restitution e becomes the unloading factor
(phi(e) - m) / (phi(e0) - m), phi the engine's own map from restitution to unloading factor
at the world's substep (``World.restitution_to_unloading``), tabulated once and interpolated
linearly (differentiable), so a pair at the scene's restitution rebounds with e exactly as a scene
written with e would. The stiffness factor leaves the restitution map where it is (in continuous
time a hysteretic spring's restitution does not depend on its stiffness).

Reported values (``values``): the friction coefficient and restitution of a pair at the scene's
values, and the stiffness as omega_0^2 f_k, the contact stiffness per kilogram of body mass
(N/m per kg; the scene's ``contact-frequency`` squared).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from dejaview.errors import SceneError
from dejaview.sim.restitution import UNLOAD_MIN

NAMES = ("friction", "restitution", "stiffness")
"""The physics parameters, in the order of every (B, 3) physics tensor."""

TABLE_POINTS = 257
"""Restitutions at which the restitution-to-unloading map is tabulated (0 to 1)."""


@functools.lru_cache(maxsize=16)
def _unloading_table(omega_h: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(restitutions, unloading factors) of the engine's map at substep ``omega_h``, where it
    is strictly increasing (below the restitution the integrator gives at phi = ``UNLOAD_MIN``,
    phi is that)."""
    from dejaview.sim.world import _discrete_restitution, restitution_to_unloading

    floor = _discrete_restitution(UNLOAD_MIN, omega_h)
    es = [floor + (1.0 - floor) * i / (TABLE_POINTS - 1) for i in range(TABLE_POINTS)]
    phis = [UNLOAD_MIN] + [restitution_to_unloading(e, omega_h) for e in es[1:]]
    return tuple(es), tuple(phis)


@dataclass(frozen=True)
class PhysicsModel:
    """The inferred physics of one scene: which parameters are free, their priors and the
    scene's values they are centred on.

    Attributes:
        sd: (friction, restitution, stiffness) relative standard deviations (0: known).
        friction, restitution: the scene's values (``<simulation>``).
        omega_h: the world's contact frequency times its substep.
        frequency: the world's contact frequency omega_0 (rad/s).
    """

    sd: tuple[float, float, float]
    friction: float
    restitution: float
    omega_h: float
    frequency: float

    @staticmethod
    def from_scene(scene, world) -> "PhysicsModel | None":
        """The scene's ``<physics-prior>`` for ``world``; None where absent or all zero.

        Raises:
            SceneError: a restitution prior on a scene whose restitution the engine cannot move
                (0, or below the least the integrator gives).
        """
        if scene.inference is None or not scene.inference.infers_physics:
            return None
        prior = scene.inference.physics_prior
        sd = tuple(float(getattr(prior, n) or 0.0) for n in NAMES)
        h = world.dt / world.substeps
        model = PhysicsModel(sd, float(scene.simulation.friction), float(scene.simulation.restitution),
                             world.contact.frequency * h, world.contact.frequency)
        if sd[1] > 0 and model._phi0 <= UNLOAD_MIN:
            es, _ = _unloading_table(model.omega_h)
            raise SceneError(f"<physics-prior restitution>: the scene's restitution {model.restitution:g} is at or "
                             f"below the least this step resolves ({es[0]:.3f}); a relative prior cannot move it "
                             f"(give <simulation restitution> a value above it, or leave restitution out)")
        return model

    @property
    def free(self) -> tuple[int, ...]:
        """Indices (into ``NAMES``) of the inferred parameters."""
        return tuple(i for i, s in enumerate(self.sd) if s > 0)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(NAMES[i] for i in self.free)

    @functools.cached_property
    def _table(self) -> tuple[torch.Tensor, torch.Tensor]:
        es, phis = _unloading_table(self.omega_h)
        return torch.tensor(es, dtype=torch.float64), torch.tensor(phis, dtype=torch.float64)

    @functools.cached_property
    def _phi0(self) -> float:
        return float(self._unloading(torch.tensor([self.restitution], dtype=torch.float64))[0])

    def _unloading(self, e: torch.Tensor) -> torch.Tensor:
        """phi(e) (same shape), linear between the table's points."""
        es, phis = self._table
        e = e.clamp(float(es[0]), 1.0)
        i = torch.searchsorted(es, e.detach()).clamp(1, len(es) - 1)
        e0, e1 = es[i - 1], es[i]
        p0, p1 = phis[i - 1], phis[i]
        return p0 + (p1 - p0) * (e - e0) / (e1 - e0)

    def full(self, z: torch.Tensor) -> torch.Tensor:
        """(B, 3) standard normals of all three parameters from the free ones' z (B, F)."""
        out = z.new_zeros(z.shape[0], 3)
        cols = [z[:, j] for j in range(z.shape[1])]
        parts = [out[:, i] for i in range(3)]
        for j, i in enumerate(self.free):
            parts[i] = cols[j]
        return torch.stack(parts, -1)

    def _restitution(self, zz: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """(B,) min(1, e0 exp(s_e z_e)) of all three standard normals zz (B, 3), deviations s (3,)."""
        return torch.clamp(self.restitution * torch.exp(s[1] * zz[:, 1]), max=1.0)

    def values(self, z: torch.Tensor) -> torch.Tensor:
        """(B, 3) friction coefficient, restitution and stiffness (omega_0^2 f_k, N/m per kg) of
        the free parameters' standard normals z (B, F)."""
        zz = self.full(z)
        s = torch.tensor(self.sd, dtype=zz.dtype)
        friction = self.friction * torch.exp(s[0] * zz[:, 0])
        restitution = self._restitution(zz, s)
        stiffness = self.frequency ** 2 * torch.exp(s[2] * zz[:, 2])
        return torch.stack([friction, restitution, stiffness], -1)

    def engine_logs(self, z: torch.Tensor) -> torch.Tensor:
        """(B, 3) the engines' physics (``World.physics``: logs of the factors on friction,
        unloading and stiffness) of standard normals z (B, F); differentiable."""
        zz = self.full(z)
        s = torch.tensor(self.sd, dtype=zz.dtype)
        log_mu = s[0] * zz[:, 0]
        log_k = s[2] * zz[:, 2]
        if self.sd[1] > 0:
            log_phi = torch.log((self._unloading(self._restitution(zz, s)) - UNLOAD_MIN).clamp_min(1e-300)
                                / (self._phi0 - UNLOAD_MIN))
        else:
            log_phi = torch.zeros_like(log_mu)
        return torch.stack([log_mu, log_phi, log_k], -1)

    def to_json(self) -> dict:
        """``result.json``'s ``physics.prior``."""
        return {"friction": self.sd[0], "restitution": self.sd[1], "stiffness": self.sd[2],
                "centre": {"friction": self.friction, "restitution": self.restitution,
                           "stiffness": self.frequency ** 2},
                "units": {"stiffness": "N/m per kg of body mass (contact-frequency squared)"}}


def candidate_material(physics: torch.Tensor, mu: torch.Tensor, unload: torch.Tensor, stiff: torch.Tensor):
    """Each candidate's physics (``World.physics``, (B, 3) logs of factors) applied to a contact
    law's friction, unloading factor and stiffness, each with the batch first (size 1 or B); the
    factors broadcast over the other dims. The unloading factor's acts on its height above the
    least, phi' = m + f (phi - m) with m = ``UNLOAD_MIN`` (written phi f + m (1 - f): phi itself at
    f = 1), capped at 1."""
    f = torch.exp(physics)

    def per_candidate(column: int, like: torch.Tensor) -> torch.Tensor:
        return f[:, column].reshape((-1,) + (1,) * (like.dim() - 1))

    fu = per_candidate(1, unload)
    return (mu * per_candidate(0, mu), torch.clamp(unload * fu + UNLOAD_MIN * (1.0 - fu), max=1.0),
            stiff * per_candidate(2, stiff))
