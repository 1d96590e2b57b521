"""System identification: one friction, restitution and stiffness shared by several scenes.

The same objects thrown several times (each scene its own start and observations, tracked ones
best) share one physics. The joint posterior over every scene's start and the shared physics is

    -log p(x_1..x_S, z | ends) = sum_s 0.5 |R_s(x_s, z)|^2 + 0.5 |z|^2 + const,

R_s a scene's observation and start-prior residuals (``Posterior.residuals`` without its physics
prior), z the physics' standard normals (``dejaview.sim.physics``), counted once.

``identify`` finds its maximum in steps: each scene's own most probable past with the physics free
(``MapSearch`` on the scene's ``Posterior``); Levenberg-Marquardt on the joint vector from the best
of each scene's physics and their mean (exact Jacobians: a scene's residuals see only its start and
z); then the physics scanned over its prior, each scene's start refined at each node, and the
joint refined from the best nodes (``physics_marginal.scan``: tracked bounces are explained by
more than one restitution); then, ``rounds`` times while it gains, each scene's start searched again with the physics fixed
at the joint maximum's (``physics_fixed``: a search in the start alone finds a tumbling box's basin
that one with the physics free misses) and the joint refined again; finally the Laplace
approximation at the maximum, (J^T J)^-1, and the physics' marginal posterior on a grid around it,
each scene's start integrated out (``physics_marginal.physics_grid``), for the intervals.
With ``samples``, draws from that Gaussian are weighted by the exact joint posterior over it
(importance sampling; the effective sample size is reported), so the intervals hold where the
Gaussian is off, as long as it covers the posterior.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from dejaview.errors import InferenceError
from dejaview.inference.params import IdentifyParams


def shared_scenes(scenes: list, params: IdentifyParams) -> list:
    """The scenes with one physics prior (their own, all the same, or ``params``'), checked to
    describe the same objects and the same nominal physics.

    Raises:
        InferenceError: fewer than two scenes; a scene without inference; scenes with other
            movable objects, another source, other friction or restitution, or other physics priors
            (naming the scene and what differs).
    """
    from dejaview.scene import PhysicsPrior

    if len(scenes) < 2:
        raise InferenceError("identify needs at least two scenes of the same objects")
    first = scenes[0]

    def name(sc) -> str:
        return str(sc.path) if sc.path is not None else (sc.name or "<scene>")

    def movable(sc) -> set:
        return {o.id for o in sc.objects if not o.fixed}

    priors = set()
    for sc in scenes:
        if sc.inference is None:
            raise InferenceError(f"{name(sc)}: the scene has no <inference> section")
        if sc.inference.source != first.inference.source:
            raise InferenceError(f"{name(sc)}: its source is {sc.inference.source!r}, {name(first)}'s "
                                 f"{first.inference.source!r}: identify needs the same object in every scene")
        if movable(sc) != movable(first):
            missing = sorted(movable(first) - movable(sc))
            extra = sorted(movable(sc) - movable(first))
            raise InferenceError(f"{name(sc)}: not the objects of {name(first)} (missing: {', '.join(missing) or '-'}; "
                                 f"not in {name(first)}: {', '.join(extra) or '-'})")
        for attr in ("friction", "restitution"):
            if getattr(sc.simulation, attr) != getattr(first.simulation, attr):
                raise InferenceError(f"{name(sc)}: <simulation {attr}> {getattr(sc.simulation, attr)} differs from "
                                     f"{name(first)}'s {getattr(first.simulation, attr)}: a shared physics needs one")
        priors.add(sc.inference.physics_prior)
    given = {p for p in priors if p is not None}
    if len(given) > 1:
        raise InferenceError("the scenes' <physics-prior> elements differ: give them one (or leave them out)")
    prior = next(iter(given)) if given else PhysicsPrior(params.friction or None, params.restitution or None,
                                                          params.stiffness or None)
    return [replace(sc, inference=replace(sc.inference, physics_prior=prior)) for sc in scenes]


class JointPosterior:
    """The scenes' ``Posterior``s sharing their physics: parameters (B, sum_s P0_s + F), each
    scene's start columns in scene order, then the F physics columns."""

    def __init__(self, posts: list):
        self.posts = posts
        names = {p.layout.physics_names for p in posts}
        if len(names) != 1 or not next(iter(names)):
            raise InferenceError("identify: the scenes infer different physics parameters")
        self.f = len(next(iter(names)))
        self.sizes = [p.layout.start_size for p in posts]
        self.size = sum(self.sizes) + self.f

    def split(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Each scene's parameters (B, P_s): its start columns and the shared physics."""
        z = x[:, -self.f:]
        out, at = [], 0
        for n in self.sizes:
            out.append(torch.cat([x[:, at:at + n], z], -1))
            at += n
        return out

    def join(self, xs: list[torch.Tensor], z: torch.Tensor) -> torch.Tensor:
        """(B, P) from each scene's start columns (B, P_s, physics ignored) and z (B, F)."""
        return torch.cat([x[:, :n] for x, n in zip(xs, self.sizes)] + [z], -1)

    def cost(self, x: torch.Tensor) -> torch.Tensor:
        """Negative log joint posterior (B,) (inf where a scene's start is infeasible or its rollout
        not finite): the scenes' costs, each holding the physics prior once, less S - 1 of it."""
        z = x[:, -self.f:]
        total = sum(p.cost(xs)[0] for p, xs in zip(self.posts, self.split(x)))
        return total - (len(self.posts) - 1) * 0.5 * (z * z).sum(-1)

    def log_density(self, x: torch.Tensor) -> torch.Tensor:
        """Unnormalised log joint posterior density (B,) with each start's base measure."""
        from dejaview.inference.reference import log_base_density

        out = -self.cost(x)
        for p, xs in zip(self.posts, self.split(x)):
            out = out + log_base_density(p, xs)
        return torch.where(torch.isfinite(out), out, torch.full_like(out, -math.inf))

    def jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals (B, M) and their Jacobian (B, M, P): each scene's without its physics prior
        columns (the last F), then z once."""
        b = x.shape[0]
        rows_r, rows_j, at = [], [], 0
        for p, xs, n in zip(self.posts, self.split(x), self.sizes):
            r, J = p.jacobian(xs)
            r, J = r[:, :-self.f], J[:, :-self.f]
            full = x.new_zeros(b, r.shape[1], self.size)
            full[:, :, at:at + n] = J[:, :, :n]
            full[:, :, -self.f:] = J[:, :, n:]
            rows_r.append(r)
            rows_j.append(full)
            at += n
        z = x[:, -self.f:]
        eye = x.new_zeros(b, self.f, self.size)
        eye[:, :, -self.f:] = torch.eye(self.f, dtype=x.dtype)
        return torch.cat(rows_r + [z], 1), torch.cat(rows_j + [eye], 1)


def levenberg_marquardt(joint: JointPosterior, x: torch.Tensor, iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Levenberg-Marquardt from each row of x (K, P) on the joint posterior; (x, cost) refined."""
    from dejaview.inference.search import levenberg_marquardt as lm

    x, cost, _, _ = lm(x, joint.cost, lambda xs, rows: joint.jacobian(xs), iterations, tolerance=1e-10)
    return x, cost


@dataclass
class IdentifyResult:
    """What ``identify`` found.

    Attributes:
        scenes: the scenes (with the physics prior used).
        joint: the ``JointPosterior``.
        x: (P,) the most probable joint parameters; cost: their negative log posterior.
        covariance: (P, P) the Laplace approximation's.
        samples: (N, P) importance samples and weights (N,), or None; ess: their effective size.
        grid: the physics' marginal posterior on a grid (``physics_marginal.PhysicsGrid``), or None.
        seconds: wall time.
        notes: warnings for the user (one line each).
    """

    scenes: list
    joint: JointPosterior
    x: torch.Tensor
    cost: float
    covariance: torch.Tensor
    samples: torch.Tensor | None = None
    weights: torch.Tensor | None = None
    ess: float | None = None
    grid: object = None
    seconds: float = 0.0
    notes: list = field(default_factory=list)

    @property
    def model(self):
        return self.joint.posts[0].layout.physics

    def physics(self) -> dict:
        """``result.json``'s ``physics``: the most probable values, each inferred one's median and
        central intervals (the grid's marginal where computed, else weighted samples where drawn,
        else the Laplace Gaussian's), the prior."""
        from dejaview.inference.physics_marginal import marginal_quantiles
        from dejaview.inference.posterior_report import (PHYSICS_COLUMNS, interval_entry, interval_levels,
                                                         weighted_quantiles)

        model, f = self.model, self.joint.f
        values = model.values(self.x[None, -f:])[0].tolist()
        qs = interval_levels()
        if self.grid is not None:
            quant = marginal_quantiles(self.grid, model, qs)
            how = "marginal posterior on a grid of the physics, each start integrated out (nested Laplace)"
        elif self.samples is not None:
            quant = weighted_quantiles(model.values(self.samples[:, -f:]), self.weights, qs)
            how = "importance samples of the joint posterior"
        else:  # each value is monotone in its own z: the Gaussian's quantiles map through
            sd = torch.sqrt(torch.diagonal(self.covariance)[-f:].clamp_min(0))
            normal = torch.distributions.Normal(0.0, 1.0)
            z = torch.stack([self.x[-f:] + sd * float(normal.icdf(torch.tensor(q))) for q in qs])
            quant = model.values(z)
            how = "Laplace approximation at the most probable joint past"
        intervals = {PHYSICS_COLUMNS[i]: interval_entry(quant, i) for i in model.free}
        return {"most_probable": dict(zip(PHYSICS_COLUMNS, values)), "inferred": list(model.names),
                "intervals": intervals, "intervals_from": how, "prior": model.to_json()}

    @property
    def names(self) -> list[str]:
        """Each scene's name in the outputs: its ``name``, else its file's stem, else ``scene-K``."""
        return [sc.name or (sc.path.stem if sc.path is not None else f"scene-{k + 1}")
                for k, sc in enumerate(self.scenes)]

    def to_json(self) -> dict:
        out = {"physics": self.physics(), "neg_log_posterior": self.cost, "seconds": self.seconds,
               "warnings": list(self.notes), "scenes": []}
        for sc, name, post, xs in zip(self.scenes, self.names, self.joint.posts, self.joint.split(self.x[None])):
            with torch.no_grad():
                state = {k: v[0].tolist() for k, v in post.layout.decode(xs).items()}
                chi2 = float(post.cost(xs)[1][0])
            out["scenes"].append({"name": name, "file": None if sc.path is None else str(sc.path),
                                  "initial_state": state, "observation_chi2": chi2,
                                  "observed": post.num_observed})
        if self.samples is not None:
            out["samples"] = {"count": int(self.samples.shape[0]), "effective": self.ess}
        if self.grid is not None:
            out["grid"] = {"nodes": int(self.grid.z.shape[0]), "passes": self.grid.passes,
                           "half_widths": [float(w) for w in self.grid.widths],
                           "effective_nodes": float(1.0 / (self.grid.weights ** 2).sum())}
        return out

    def write(self, out_dir) -> dict[str, Path]:
        """``result.json`` and, with samples, ``posterior.csv`` (each scene's start columns prefixed
        by its name, then friction, restitution, stiffness) into ``out_dir``, whole or not at all
        (``dejaview.result_set``)."""
        from dejaview.result_set import write_result_set

        return write_result_set(out_dir, self._write_files, ("result.json", "posterior.csv"))

    def _write_files(self, out: Path) -> dict[str, Path]:
        import json

        from dejaview.inference.posterior_report import CSV_HEADER, PHYSICS_COLUMNS, state_rows, write_rows

        paths = {"result": out / "result.json"}
        paths["result"].write_text(json.dumps(self.to_json(), indent=2), encoding="utf-8")
        if self.samples is not None:
            header, cols = ["sample", "weight"], []
            for name, post, xs in zip(self.names, self.joint.posts, self.joint.split(self.samples)):
                header += [f"{name}.{c}" for c in CSV_HEADER[2:]]
                cols.append(state_rows(post.layout, xs))
            header += list(PHYSICS_COLUMNS)
            cols.append(self.model.values(self.samples[:, -self.joint.f:]))
            paths["posterior"] = write_rows(out / "posterior.csv", header, self.weights, torch.cat(cols, -1))
        return paths


def identify(scenes: list, params: IdentifyParams | None = None, *, callback=None) -> IdentifyResult:
    """The physics several scenes of the same objects share, and each scene's start.

    Args:
        scenes: Scenes (or paths), each with its own ``<inference>`` (source, observations).
        params: ``IdentifyParams``.
        callback: called with a line of text as each stage ends (progress).
    Returns:
        IdentifyResult.
    Raises:
        InferenceError: scenes that do not share their objects or physics (``shared_scenes``),
            or no finite joint posterior anywhere the searches went.
    """
    from dejaview.inference.posterior import Posterior
    from dejaview.inference.search import MapSearch
    from dejaview.scene import Scene

    params = IdentifyParams() if params is None else params
    t0 = time.perf_counter()
    scenes = [s if hasattr(s, "objects") else Scene.from_xml(s) for s in scenes]
    scenes = shared_scenes(scenes, params)
    posts, found = [], []
    for k, sc in enumerate(scenes):
        post = Posterior.from_scene(sc)
        opt = MapSearch(replace(params.search, seed=params.seed + k)).run(post)
        if not math.isfinite(opt.loss):
            raise InferenceError(f"{sc.name or k}: no start with a finite posterior was found")
        posts.append(post)
        found.append(opt.x.to(torch.float64)[None])
        if callback is not None:
            callback(f"scene {k + 1}/{len(scenes)} searched ({post.rollouts} rollouts)")
    joint = JointPosterior(posts)
    zs = torch.cat([x[:, -joint.f:] for x in found])
    inits = torch.cat([zs, zs.mean(0, keepdim=True)])
    x0 = torch.cat([joint.join(found, z[None].expand(1, -1)) for z in inits])
    with torch.no_grad():
        first = joint.cost(x0)  # refine the best start only: a joint Jacobian costs a reverse pass per residual
    x, cost = levenberg_marquardt(joint, x0[int(torch.argmin(first))][None], params.lm_iterations)
    if not math.isfinite(float(cost[0])):
        raise InferenceError("identify: no joint start of the scenes has a finite posterior")
    x, cost = x[0], float(cost[0])
    if params.scan:  # the physics over its prior: another restitution may explain the throws better
        from dejaview.inference.physics_marginal import scan

        trial = scan(joint, x, params)
        if trial.shape[0]:
            x_new, c_new = levenberg_marquardt(joint, trial, params.lm_iterations)
            best = int(torch.argmin(c_new))
            if float(c_new[best]) < cost:
                x, cost = x_new[best], float(c_new[best])
        if callback is not None:
            callback(f"physics scanned over its prior (-log posterior {cost:.4g})")
    model = posts[0].layout.physics
    for round_ in range(params.rounds if "stiffness" not in model.names else 0):
        # the starts searched again under the joint physics (a search with the physics fixed finds a
        # tumbling box's basin that one with the physics free misses), then the joint refined again
        z = x[-joint.f:][None]
        starts = []
        for k, sc in enumerate(scenes):
            fixed = Posterior.from_scene(physics_fixed(sc, model, z))
            opt = MapSearch(replace(params.search, seed=params.seed + 101 * (round_ + 1) + k)).run(fixed)
            starts.append(opt.x.to(torch.float64)[None])
        trial = torch.cat([joint.join(starts, z), x[None]])
        with torch.no_grad():
            costs = joint.cost(trial)
        if float(costs[0]) >= cost:
            break  # the searches found nothing better than the joint maximum
        x_new, c_new = levenberg_marquardt(joint, trial[:1], params.lm_iterations)
        if not float(c_new[0]) < cost:
            break
        x, cost = x_new[0], float(c_new[0])
        if callback is not None:
            callback(f"round {round_ + 2}: starts searched again under the joint physics "
                     f"(-log posterior {cost:.4g})")
    _, J = joint.jacobian(x[None])
    H = J[0].T @ J[0]
    covariance = torch.linalg.pinv(H, hermitian=True)
    result = IdentifyResult(scenes, joint, x, cost, covariance)
    if callback is not None:
        callback(f"joint most probable physics found (-log posterior {cost:.4g})")
    if params.grid:
        from dejaview.inference.physics_marginal import physics_grid

        result.grid = physics_grid(joint, x, covariance, params)
        if callback is not None:
            callback(f"physics' marginal posterior on {result.grid.z.shape[0]} nodes "
                     f"({result.grid.passes} grid(s), half-widths {[round(float(w), 3) for w in result.grid.widths]})")
    if params.samples:
        samples, weights, ess = _importance_samples(joint, x, covariance, params)
        if math.isfinite(ess) and ess >= params.min_ess_share * params.samples:
            result.samples, result.weights, result.ess = samples, weights, ess
        else:
            result.notes.append(f"the importance samples' effective size ({ess:.1f} of {params.samples}) is too small "
                                f"to trust: the intervals are the Laplace approximation's")
    result.seconds = time.perf_counter() - t0
    return result


def physics_fixed(scene, model, z: torch.Tensor):
    """``scene`` with the physics of standard normals z (1, F) written in and no physics prior: the
    scene's friction and restitution, and every object's own, scaled as ``PhysicsModel`` scales
    them (the stiffness is not written: ``identify`` does not search again where it is inferred)."""
    values = model.values(z)[0]
    f = float(values[0]) / model.friction
    r = float(values[1]) / model.restitution

    def material(obj):
        return replace(obj, friction=None if obj.friction is None else obj.friction * f,
                       restitution=None if obj.restitution is None else min(1.0, obj.restitution * r))

    sim = replace(scene.simulation, friction=float(values[0]), restitution=float(values[1]))
    return replace(scene, simulation=sim, objects=tuple(material(o) for o in scene.objects),
                   inference=replace(scene.inference, physics_prior=None))


def _importance_samples(joint: JointPosterior, x: torch.Tensor, covariance: torch.Tensor,
                        params: IdentifyParams) -> tuple[torch.Tensor, torch.Tensor, float]:
    """``params.samples`` draws (N, P) of the Laplace Gaussian at x, weighted (N,) by the exact
    joint posterior over it, and their effective sample size (Kish)."""
    gen = torch.Generator().manual_seed(int(params.seed) * 7919 + 5)
    cov = 0.5 * (covariance + covariance.T) + 1e-12 * torch.eye(x.numel(), dtype=x.dtype)
    q = torch.distributions.MultivariateNormal(x, covariance_matrix=cov)
    eps = torch.randn(params.samples, x.numel(), generator=gen, dtype=x.dtype)
    draws = x + eps @ q.scale_tril.T
    with torch.no_grad():
        logw = joint.log_density(draws) - q.log_prob(draws)
    logw = torch.where(torch.isfinite(logw), logw, torch.full_like(logw, -math.inf))
    if not bool(torch.isfinite(logw).any()):
        return draws, torch.zeros_like(logw), 0.0
    w = torch.softmax(logw, 0)
    return draws, w, float(1.0 / (w * w).sum())
