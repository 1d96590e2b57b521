r"""Contact forces between sphere packings and static geometry, and between bodies.

Model (a penalty model normalised per body, with regularised Coulomb friction)
-------------------------------------------------------------------------------
Every sphere i (centre p_i, radius r_i) of a body is tested against every
static shape (signed distance d(p), normal n = grad d) and against the spheres
of every other body. Its penetration depth is

    delta_i = max(0, r_i - d(p_i))                  (sphere vs static)
    delta_ij = max(0, r_i + r_j - |p_j - p_i|)      (sphere vs sphere)

The stiffness of a contact *set* (one body against all statics, or one pair of
bodies) is fixed at the body level, ``k = m omega_0^2`` with m the body mass
(reduced mass for a pair), and shared among the touching spheres in
proportion to their depth, with weights ``w_i = delta_i / sum_j delta_j``:

    f_n,i = w_i k delta_i (phi + (1 - phi) s_i),   s_i = sigmoid(-v_n,i / v_s)

where v_n,i is the normal velocity of the contact point (negative when
approaching). The contact is stiffer while loading (k) than while unloading
(phi k): it returns the fraction phi of the stored energy, so the restitution
is e = sqrt(phi) in continuous time; phi is calibrated against the discrete
integrator (``World.restitution_to_unloading``) so that a simulated head-on
impact rebounds with exactly e. Unlike a linear damper this force never
pulls and never has to be clipped, and any e in [0, 1] is reachable; s_i
blends the two stiffnesses over a few mm/s (v_s) so the force stays
differentiable. A body therefore behaves like one spring of natural frequency
omega_0 however many of its spheres touch, which keeps the explicit
integrator stable (omega_0 h = 0.5 by default) and makes restitution
independent of the packing. The weights are continuous in the state: a
sphere that starts touching enters with weight zero.

Friction is Coulomb's law made smooth:

    f_t,i = -mu f_n,i v_t,i / sqrt(|v_t,i|^2 + eps^2),
    eps = eps_0 + kappa mu h F_n / m

where v_t,i is the tangential velocity of the contact point, F_n the total
normal force of the contact set and kappa = 1 + m r^2 / I_min accounts for the
rotational lightening of the effective mass. The second term of eps keeps the
viscous slope of the regularised law below m / h, so the explicit step never
overshoots the sticking velocity, even during hard impacts; in steady sliding
(|v_t| >> eps) the force is mu f_n to within (eps / v_t)^2 / 2.

Contact points are on the sphere surface along the normal; torques are taken
about the centre of mass. All functions are free of data-dependent Python
branches, so they run under ``torch.func`` transforms and ``torch.compile``.
"""

from __future__ import annotations

import torch


def normal_force(depth: torch.Tensor, normal_velocity: torch.Tensor, stiffness: torch.Tensor,
                 unload: torch.Tensor, unload_velocity: float) -> torch.Tensor:
    """Depth-weighted hysteretic spring normal forces of one contact set.

    Args:
        depth: (B, C) penetration depths (>= 0) of the C candidate contacts of each set.
        normal_velocity: (B, C) normal velocity of each contact point (negative approaching).
        stiffness: broadcastable to (B, C), body-level stiffness k.
        unload: broadcastable to (B, C), unloading stiffness factor phi in [0, 1].
        unload_velocity: blending speed v_s (m/s) between loading and unloading.
    Returns:
        (B, C) normal force magnitudes (>= 0).
    """
    total = depth.sum(-1, keepdim=True)
    tiny = torch.finfo(depth.dtype).tiny
    weight = depth / (total + tiny)
    loading = torch.sigmoid(-normal_velocity / unload_velocity)
    return weight * stiffness * depth * (unload + (1.0 - unload) * loading)


def friction_force(tangential_velocity: torch.Tensor, normal: torch.Tensor, mu: torch.Tensor,
                   eps: torch.Tensor) -> torch.Tensor:
    """Regularised Coulomb friction forces.

    Args:
        tangential_velocity: (..., 3) tangential velocity of each contact point.
        normal: (...) normal force magnitudes.
        mu: broadcastable to (...), friction coefficients.
        eps: broadcastable to (...), regularisation speeds (> 0).
    Returns:
        (..., 3) friction forces opposing the tangential velocity.
    """
    speed = torch.sqrt((tangential_velocity * tangential_velocity).sum(-1) + eps * eps)
    return -(mu * normal / speed).unsqueeze(-1) * tangential_velocity


def _point_velocity(v: torch.Tensor, w: torch.Tensor, arm: torch.Tensor) -> torch.Tensor:
    return v + torch.linalg.cross(w.expand_as(arm), arm, dim=-1)


def static_contact_wrench(world, state, spheres: torch.Tensor, h: float):
    """Force and torque on every body from contacts with all static shapes.

    Args:
        world: the World.
        state: current State, (B, N, ...).
        spheres: (B, N, S, 3) world sphere centres.
        h: integration substep (s), for the friction regularisation.
    Returns:
        force (B, N, 3), torque (B, N, 3) about each centre of mass.
    """
    if not world.statics:
        z = torch.zeros_like(state.position)
        return z, z
    radii = world.radii  # (N, S)
    arms_c = spheres - state.position.unsqueeze(-2)  # (B, N, S, 3)
    depths, normals, arms, vels = [], [], [], []
    for shape in world.statics:
        d, n = shape.distance(spheres)  # (B, N, S), (B, N, S, 3)
        depths.append(torch.relu(radii - d) * world.mask)
        arm = arms_c - n * radii.unsqueeze(-1)
        normals.append(n)
        arms.append(arm)
    depth = torch.stack(depths, 2)  # (B, N, K, S)
    normal = torch.stack(normals, 2)  # (B, N, K, S, 3)
    arm = torch.stack(arms, 2)
    v = state.linear_velocity[:, :, None, None, :]
    w = state.angular_velocity[:, :, None, None, :]
    vel = _point_velocity(v, w, arm)
    vn = (vel * normal).sum(-1)
    vt = vel - vn.unsqueeze(-1) * normal
    b, nb, k, s = depth.shape
    m = world.mass  # (N,)
    omega = world.contact.frequency
    stiff = (m * omega ** 2)[None, :, None]  # (1, N, 1)
    unload = world.unload_static[None, :, :, None].expand(b, nb, k, s).reshape(b, nb, k * s)
    fn = normal_force(depth.reshape(b, nb, k * s), vn.reshape(b, nb, k * s), stiff, unload,
                      world.contact.unload_velocity)
    fn = fn.reshape(b, nb, k, s)
    total = fn.sum((-1, -2))  # (B, N)
    mu = world.mu_static[None, :, :, None]  # (1, N, K, 1)
    mu_max = world.mu_static.max(-1).values  # (N,)
    eps = world.contact.friction_velocity + world.kappa * mu_max * h * total / m  # (B, N)
    ft = friction_force(vt, fn, mu, eps[:, :, None, None])
    force = fn.unsqueeze(-1) * normal + ft  # (B, N, K, S, 3)
    torque = torch.linalg.cross(arm, force, dim=-1)
    return force.sum((2, 3)), torque.sum((2, 3))


def pair_contact_wrench(world, state, spheres: torch.Tensor, h: float, pair_ids=None):
    """Force and torque on every body from sphere-sphere contacts between movable bodies.

    Args:
        world: the World.
        state: current State.
        spheres: (B, N, S, 3) world sphere centres.
        h: integration substep (s).
        pair_ids: indices into ``world.pairs`` to evaluate (None: all). The
            caller's broad phase passes only pairs whose bounding spheres overlap.
    Returns:
        force (B, N, 3), torque (B, N, 3).
    """
    force = torch.zeros_like(state.position)
    torque = torch.zeros_like(state.position)
    if world.pairs.shape[0] == 0:
        return force, torque
    pairs = world.pairs if pair_ids is None else world.pairs[pair_ids]
    mu_p = world.mu_pair if pair_ids is None else world.mu_pair[pair_ids]
    unload_p = world.unload_pair if pair_ids is None else world.unload_pair[pair_ids]
    mass_p = world.mass_pair if pair_ids is None else world.mass_pair[pair_ids]
    kappa_p = world.kappa_pair if pair_ids is None else world.kappa_pair[pair_ids]
    if pairs.shape[0] == 0:
        return force, torque
    ia, ib = pairs[:, 0], pairs[:, 1]
    pa, pb = spheres[:, ia], spheres[:, ib]  # (B, P, S, 3)
    ra, rb = world.radii[ia], world.radii[ib]  # (P, S)
    ma, mb = world.mask[ia], world.mask[ib]
    diff = pb.unsqueeze(-3) - pa.unsqueeze(-2)  # (B, P, S, S, 3) from a_i to b_j
    sq = (diff * diff).sum(-1)
    dist = torch.sqrt(sq + 1e-24)
    n = diff / dist.unsqueeze(-1)
    depth = torch.relu(ra.unsqueeze(-1) + rb.unsqueeze(-2) - dist) * (ma.unsqueeze(-1) * mb.unsqueeze(-2))
    point = pa.unsqueeze(-2) + n * ra[..., :, None, None]  # contact point on a's sphere
    xa = state.position[:, ia][:, :, None, None, :]
    xb = state.position[:, ib][:, :, None, None, :]
    arm_a, arm_b = point - xa, point - xb
    va = _point_velocity(state.linear_velocity[:, ia][:, :, None, None, :],
                         state.angular_velocity[:, ia][:, :, None, None, :], arm_a)
    vb = _point_velocity(state.linear_velocity[:, ib][:, :, None, None, :],
                         state.angular_velocity[:, ib][:, :, None, None, :], arm_b)
    vrel = vb - va
    vn = (vrel * n).sum(-1)  # separating > 0
    vt = vrel - vn.unsqueeze(-1) * n
    b, p, s1, s2 = depth.shape
    omega = world.contact.frequency
    stiff = (mass_p * omega ** 2)[None, :, None]
    unload = unload_p[None, :, None]
    fn = normal_force(depth.reshape(b, p, s1 * s2), vn.reshape(b, p, s1 * s2), stiff, unload,
                      world.contact.unload_velocity)
    fn = fn.reshape(b, p, s1, s2)
    total = fn.sum((-1, -2))  # (B, P)
    eps = world.contact.friction_velocity + kappa_p * mu_p * h * total / mass_p
    ft = friction_force(vt, fn, mu_p[None, :, None, None], eps[:, :, None, None])
    f_b = fn.unsqueeze(-1) * n + ft  # on b
    fa_tot = -f_b.sum((2, 3))
    fb_tot = f_b.sum((2, 3))
    ta = torch.linalg.cross(arm_a, -f_b, dim=-1).sum((2, 3))
    tb = torch.linalg.cross(arm_b, f_b, dim=-1).sum((2, 3))
    force = force.index_add(1, ia, fa_tot).index_add(1, ib, fb_tot)
    torque = torque.index_add(1, ia, ta).index_add(1, ib, tb)
    return force, torque


def pair_bounding_overlap(world, state, margin: float = 0.0) -> torch.Tensor:
    """Broad phase: which body pairs' bounding spheres overlap in any batch element.

    Returns:
        (P,) bool.
    """
    ia, ib = world.pairs[:, 0], world.pairs[:, 1]
    d = torch.linalg.vector_norm(state.position[:, ia] - state.position[:, ib], dim=-1)  # (B, P)
    return (d < world.bound[ia] + world.bound[ib] + margin).any(0)
