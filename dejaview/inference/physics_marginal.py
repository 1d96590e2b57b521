"""The shared physics' marginal posterior on a grid, each scene's start integrated out by Laplace.

``identify`` (``dejaview.inference.identify``) finds the joint maximum of every scene's start and
the shared physics z (F standard normals). Its Laplace approximation at that maximum gives the
physics intervals only where the joint posterior is Gaussian: a tumbling box's tracked poses are
rough functions of the friction and restitution (exact Jacobian columns of 1,800 per standard
deviation were measured), so the curvature at the maximum says the physics is known to a hair
while the starts, moved a little, explain the throws as well at other physics.

Here the starts are integrated out at each physics instead (the nested Laplace approximation of
Rue, Martino and Chopin 2009, for a few hyperparameters shared by many latent variables): on a
tensor grid of z around the maximum, each scene's start is refined by Levenberg-Marquardt with the
physics fixed (warm-started from the maximum's), and

    log p(z | all) = -0.5 |z|^2 + sum_s [ -c_s(x_s*(z), z) + log b_s(x_s*) - 0.5 log det H_s ] + const,

c_s the scene's negative log posterior without the physics prior, b_s its start's base measure
(``reference.log_base_density``), H_s = J_s^T J_s its Gauss-Newton curvature in the start. The
grid's half-widths start at ``IdentifyParams.grid_sds`` Laplace standard deviations (at least
``grid_min_width``) and widen, each by ``grid_widen``, while the marginal holds mass at an edge.
The intervals are the weighted nodes' quantiles, mapped through the physics' monotone values.
Within one scene, another basin of the start at the same physics is not counted (the refinement
follows the maximum's basin).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch


@dataclass
class PhysicsGrid:
    """The marginal posterior of the physics on a grid.

    Attributes:
        z: (G, F) the nodes (standard normals of the inferred physics).
        log_weight: (G,) unnormalised log marginal posterior at each node (-inf: no finite fit).
        starts: (G, sum_s P0_s) each node's refined starts, scene after scene.
        widths: (F,) the grid's half-widths in z.
        passes: grids evaluated (each widening one or more axes).
    """

    z: torch.Tensor
    log_weight: torch.Tensor
    starts: torch.Tensor
    widths: torch.Tensor
    passes: int

    @property
    def weights(self) -> torch.Tensor:
        """(G,) normalised weights of the nodes."""
        lw = torch.where(torch.isfinite(self.log_weight), self.log_weight, torch.full_like(self.log_weight, -math.inf))
        return torch.softmax(lw, 0)


def _refine_starts(post, f: int, starts: torch.Tensor, z: torch.Tensor, iterations: int):
    """Levenberg-Marquardt on the start columns of one scene at fixed physics.

    Args:
        post: the scene's ``Posterior`` (with the physics prior: its last F columns and residuals).
        f: number of physics columns F.
        starts: (G, P0) the starts to refine from; z: (G, F) each row's physics.
        iterations: most iterations.
    Returns:
        (starts (G, P0), cost (G,) without the physics prior, 0.5 log det J^T J (G,)); cost inf
        where no finite start was found.
    """
    from dejaview.inference.search import levenberg_marquardt

    n = starts.shape[1]
    prior = 0.5 * (z * z).sum(-1)

    def cost_of(s):
        with torch.no_grad():
            return post.cost(torch.cat([s, z], -1))[0] - prior

    def jacobian_of(s, rows):
        r, J = post.jacobian(torch.cat([s, z[rows]], -1))
        return r[:, :-f], J[:, :-f, :n]

    x, cost, _, J = levenberg_marquardt(starts.clone(), cost_of, jacobian_of, iterations, tolerance=1e-8,
                                        jacobian_at_end=True)
    H = J.transpose(1, 2) @ J
    eye = torch.eye(n, dtype=H.dtype)
    sign, logdet = torch.linalg.slogdet(H + 1e-10 * eye * torch.diagonal(H, dim1=1, dim2=2).mean(-1)[:, None, None])
    half_logdet = torch.where(sign > 0, 0.5 * logdet, torch.full_like(logdet, math.inf))
    return x, cost, half_logdet


def _nodes(center: torch.Tensor, widths: torch.Tensor, per_axis: int) -> torch.Tensor:
    """(per_axis^F, F) the tensor grid of ``per_axis`` nodes per axis over center +- widths."""
    axes = [torch.linspace(float(c - w), float(c + w), per_axis, dtype=torch.float64) for c, w in zip(center, widths)]
    return torch.tensor(list(itertools.product(*[a.tolist() for a in axes])), dtype=torch.float64)


def evaluate(joint, x: torch.Tensor, z: torch.Tensor, iterations: int
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The log marginal posterior (G,) of the physics z (G, F), the refined starts (G, S) and the
    joint negative log posterior at them (G,): every scene's start refined at each node from the
    joint parameters x's (P,)."""
    from dejaview.inference.reference import log_base_density

    g = z.shape[0]
    prior = 0.5 * (z * z).sum(-1)
    total, joint_cost = -prior, prior.clone()
    starts = []
    for post, xs, n in zip(joint.posts, joint.split(x[None]), joint.sizes):
        s0 = xs[:, :n].expand(g, n).clone()
        s, cost, half_logdet = _refine_starts(post, joint.f, s0, z, iterations)
        base = log_base_density(post, torch.cat([s, z], -1))
        total = total - cost + base - half_logdet
        joint_cost = joint_cost + cost
        starts.append(s)
    total = torch.where(torch.isfinite(total), total, torch.full_like(total, -math.inf))
    joint_cost = torch.where(torch.isfinite(joint_cost), joint_cost, torch.full_like(joint_cost, math.inf))
    return total, torch.cat(starts, -1), joint_cost


def scan(joint, x: torch.Tensor, params) -> torch.Tensor:
    """Joint parameters (K, P) to refine from: the physics scanned over the prior (a tensor grid of
    ``scan`` nodes in all over +- ``scan_width`` standard deviations), each scene's start refined
    at each node from x's (P,), the ``scan_keep`` nodes of least joint cost.

    The joint posterior of tracked throws is multimodal in the physics (a bounce explained by
    another restitution and another start): measured on ``bench/identify_calibration.py``'s ball
    throws, the joint maximum refined from the truth cost 18.4 and 17.3 where the search's cost
    31.7 and 17.7, at a restitution 0.04-0.06 away."""
    f = joint.f
    per_axis = min(params.grid_axis, int(math.floor(params.scan ** (1.0 / f) + 1e-9)))
    per_axis = max(3, per_axis - (1 - per_axis % 2))
    z = _nodes(torch.zeros(f, dtype=torch.float64), torch.full((f,), params.scan_width, dtype=torch.float64),
               per_axis)
    _, starts, cost = evaluate(joint, x, z, params.grid_iterations)
    order = torch.argsort(cost)[: params.scan_keep]
    order = order[torch.isfinite(cost[order])]
    out, at = [], 0
    for n in joint.sizes:
        out.append(starts[order, at:at + n])
        at += n
    return joint.join(out, z[order])


def physics_grid(joint, x: torch.Tensor, covariance: torch.Tensor, params) -> PhysicsGrid:
    """The physics' marginal posterior on a grid around the joint maximum x (P,) (module docstring).

    Args:
        joint: the ``JointPosterior``.
        x: (P,) its maximum; covariance: (P, P) the Laplace approximation there (its physics block
            sets the first half-widths).
        params: ``IdentifyParams`` (``grid``, ``grid_sds``, ``grid_min_width``, ``grid_widen``,
            ``grid_passes``, ``grid_iterations``).
    Returns:
        PhysicsGrid.
    """
    f = joint.f
    per_axis = min(params.grid_axis, int(math.floor(params.grid ** (1.0 / f) + 1e-9)))
    per_axis = max(3, per_axis - (1 - per_axis % 2))  # odd: the maximum is a node
    center = x[-f:].to(torch.float64)
    sd = torch.sqrt(torch.diagonal(covariance)[-f:].clamp_min(0)).to(torch.float64)
    widths = torch.clamp(params.grid_sds * sd, min=params.grid_min_width, max=params.grid_max_width)
    passes = 0
    while True:
        passes += 1
        z = _nodes(center, widths, per_axis)
        logw, starts, _ = evaluate(joint, x, z, params.grid_iterations)
        grid = PhysicsGrid(z, logw, starts, widths.clone(), passes)
        if passes >= params.grid_passes or not bool(torch.isfinite(logw).any()):
            return grid
        top = float(logw[torch.isfinite(logw)].max())
        widen = torch.zeros(f, dtype=torch.bool)
        for d in range(f):
            edge = (z[:, d] - center[d]).abs() >= widths[d] * (1 - 1e-9)
            if bool(edge.any()) and float(logw[edge].max()) > top - params.grid_edge_nats:
                widen[d] = bool(widths[d] < params.grid_max_width)
        if not bool(widen.any()):
            return grid
        widths = torch.where(widen, torch.clamp(widths * params.grid_widen, max=params.grid_max_width), widths)


def marginal_quantiles(grid: PhysicsGrid, model, qs) -> torch.Tensor:
    """Quantiles (len(qs), 3) of the physics' values (friction, restitution, stiffness) under the
    grid's marginal: each node's weight spread evenly over its cell along each axis (a piecewise
    linear CDF), mapped through ``model.values`` (monotone in each parameter's own z)."""
    import numpy as np

    w = grid.weights
    f = grid.z.shape[1]
    zq = torch.zeros(len(qs), f, dtype=torch.float64)
    for d in range(f):
        nodes = torch.unique(grid.z[:, d])
        mass = torch.stack([w[grid.z[:, d] == v].sum() for v in nodes])
        step = float(nodes[1] - nodes[0]) if nodes.numel() > 1 else 1.0
        edges = torch.cat([nodes[:1] - step / 2, nodes + step / 2])
        cdf = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(mass, 0)])
        zq[:, d] = torch.tensor(np.interp(np.asarray(qs, dtype=float), cdf.numpy(), edges.numpy()),
                                dtype=torch.float64)
    return model.values(zq)
