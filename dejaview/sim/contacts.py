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

    f_n,i = w_i k delta_i (phi + (1 - phi) s_i)

where v_n,i is the normal velocity of the contact point (negative when
approaching). The contact is stiffer while loading (k) than while unloading
(phi k): it returns the fraction phi of the stored energy, so the restitution
is e = sqrt(phi) in continuous time; phi is calibrated against the discrete
integrator (``World.restitution_to_unloading``) so that a simulated head-on
impact rebounds with e. Unlike a linear damper this force never pulls (below e = 0.11, phi < 0
and the factor is cut off at zero: ``normal_force``). s_i blends the two stiffnesses at rest over a
few mm/s (v_s) and in an impact over a fixed part of its phase
(s_i = ``dejaview.sim.restitution.loading``). A body therefore behaves like
one spring of natural frequency omega_0 however many of its spheres touch, which keeps the explicit
integrator stable (omega_0 h = 0.25 by default) and makes restitution
independent of the packing. The weights are continuous in the state: a
sphere that starts touching enters with weight zero.

Friction is Coulomb's law with a velocity-level stick limit:

    a_i = mu f_n,i                                  (Coulomb limit)
    b_i = w_i m_i |v_t,i| / h                       (force that stops the slip in one substep)
    f_t,i = -(v_t,i / |v_t,i|) smin(a_i, b_i),      smin(a, b) = a b / (a^8 + b^8)^(1/8)

where v_t,i is the tangential velocity of the contact point, h the substep
and m_i the contact's effective mass along the slip direction t while it
slips, faded to its lower bound over all tangent directions at rest:

    1 / m_i = 1 / m + (r_i x t)^T I_w^-1 (r_i x t) + (1 - |t|^2) |r_i|^2 / I_min,
    t = v_t,i / sqrt(|v_t,i|^2 + v_eps^2),  v_eps = SLIP_EPS = 1 mm/s

(r_i the lever arm, I_w the world-frame inertia, I_min the smallest principal
moment; for a body pair the two bodies' terms add). While sliding (a << b)
this is Coulomb friction, during an impact included; near sticking (b << a)
it is a viscous force f_t,i = -c_i v_t,i, c_i = w_i m_i / h, that removes
the slip in about one substep. At rest the bound matters: stacked over the
contacts of one set a substep maps slips u to (1 - H C) u (H the contacts'
Delassus matrix, PSD with 2 x 2 tangent blocks H_ii; C = diag(h c_i)), and
with every m_i at most the true effective mass in any tangent direction,
lambda_max(H C) <= sum_i h c_i lambda_max(H_ii) <= sum_i w_i = 1: no
overshoot, in the state and in its linearisation (the gradients). Taken along
the slip direction alone, the effective mass jumps at v_t = 0 (direction
undefined; round-off slips of a resting body sat on that jump): on a resting
box reverse-mode gradients then grew without bound (``tests/sim/test_gradients.py``;
docs/benchmarks.md, "Physics measurements"). Written as
``-v_t a c / (a^8 + (c |v_t|)^8)^(1/8)`` the friction is smooth in v_t (no
division by |v_t|), so gradients stay finite at rest.

Predicted slip (static contacts). The slip v_t,i above is not the contact
point's tangential velocity at the start of the substep but the one the
substep's normal forces would leave it with:

    v_t,i <- v_t,i + h P_i (F_N / m + (I_w^-1 T_N) x r_i)

with F_N and T_N the normal force and torque of all the body's static contacts
(summed over them) and P_i the projection on contact i's tangent plane
(``predicted_slip_change``). In an impact on an edge or a corner the normal
force (hundreds of newtons over a few substeps) turns the body and drives the
contact point sideways within one substep; friction read from the slip at the
substep's start would lag one substep behind that, and the lag slip it leaves
at the peak of the impact cannot be taken back while the contact unloads
(with the small unloading stiffness of a low restitution): a box landing on an
edge, where Coulomb friction holds a rigid edge, would leave the floor sliding
and spinning faster than the rigid box (docs/physics-fidelity.md, "Impacts on
an edge or a corner", has the numbers;
``tests/sim/test_physics.py::test_box_landing_on_an_edge_leaves_it_without_slip_like_a_rigid_box``;
MuJoCo agrees with the rigid box there). With the prediction the friction is
implicit in the normal forces' part of the slip; the stick limit's
no-overshoot bound still holds (a substep maps the predicted slip u to
(1 - H C) u). For a body resting on a face F_N is normal to the surface and
T_N about zero, so nothing changes at rest. Body pairs alike, with the
relative slip and the pair's normal force and torques on both bodies
(``predicted_pair_slip_change``).

Roll stick of a line contact (static contacts). On an edge (touching
contacts along a line) the normal forces also stop the roll that lifts one
end of the line and presses the other, as a rigid edge's end forces do,
within one substep at the default step and within the contact's time scale
at finer ones (``dejaview.sim.line_contact``); not for box bodies, whose
corners do without it.

Body pairs against a box. Where one body of a pair is a box (a primitive
``box`` object: ``BodySpec.box_half``, ``World.pair_surface``) and the other
is not, the other body's spheres meet the box's exact faces, edges and
corners: each sphere i is paired with the box's closest point to its centre,
q_i = x + R clamp(R^T (p_i - x), -half, half), as with a sphere of radius 0
(``box_partner``), so delta_i = r_i - |p_i - q_i| and the normal is
(q_i - p_i) / |q_i - p_i|; the law above is unchanged. A centre that has
crossed the surface (a penetration deeper than the sphere's radius: a small
sphere in a hard impact) is paired with a large sphere behind the nearest
face, so delta_i stays r_i minus the signed distance and the force pushes it
back out through that face. The box's own spheres
stay for a pair of two boxes (sphere against sphere) and for its contacts with
curved statics (spheres, cylinders, grids). Why: a box's packing is a union of spheres, bumpy on a ball's scale;
a ball meeting a packed face 5-30 mm off a sphere's axis left it sideways at
up to 0.15 m/s where a flat face sends it straight back, and MuJoCo's box
sent a ball rolling into it 1 cm off centre 12 cm elsewhere by 1.5 s
(docs/physics-fidelity.md; ``tests/sim/test_physics.py``).

A box body's corners and static box edges. A box body meets planes and static
boxes with its 8 exact corners (spheres of 1 mm whose surfaces pass through
them) in place of its packing, and without the roll stick; where it meets a
static box, the static's edges meet the body's exact faces, and the body's
corners off the static's faces are left out (``dejaview.sim.box_edges``).

Contact points are on the sphere surface along the normal; torques are taken
about the centre of mass.

Capacity. Most candidate contacts are not touching (a resting body touches a
table with a few of its spheres; two boxes meet with a few of their S x S
sphere pairs), and every force above is exactly zero for them (w_i = 0). So
each contact set computes only its deepest candidates: per body and static
shape the ``ContactSettings.max_static_contacts`` deepest spheres, per body
pair the ``max_pair_contacts`` deepest sphere pairs. The selection (a
``topk`` of the depths, on detached values) carries no gradient; the
selected contacts' forces are recomputed from the differentiable state. While
a set has no more touching candidates than its capacity the result is that of
the dense computation, values and gradients (``tests/sim/test_contact_capacity.py``);
beyond it the shallowest contacts, which carry the least force, are dropped.
How many of the bundled bodies' spheres touch at once (and so what the
capacities must hold): ``tests/sim/test_contact_capacity.py``, docs/benchmarks.md.

All functions are free of data-dependent Python branches, so they run under
``torch.func`` transforms and ``torch.compile``.
"""

from __future__ import annotations

import torch

from dejaview.sim.box_edges import CORNER_KINDS, box_corners, on_static_edge, static_edge_contacts
from dejaview.sim.epsilons import NORMAL_EPS2, TINY
from dejaview.sim.line_contact import line_roll_stick, roll_stop_time
from dejaview.sim.motion import static_point_velocity
from dejaview.sim.physics import candidate_material
from dejaview.sim.restitution import loading
from dejaview.sim.rotation import quat_to_matrix, small_matmul

SMOOTH_MIN_POWER = 8.0  # smin(a, a) = 0.917 a; higher is closer to min but less smooth


def deepest(depth: torch.Tensor, capacity: int) -> torch.Tensor:
    """Indices (..., capacity) of the deepest candidates along the last dim of ``depth`` (..., M).

    A selection only: computed on detached values, so it carries no gradient;
    the forces of the selected contacts are recomputed from the differentiable
    state. Ties (e.g. many candidates at depth 0) are broken arbitrarily.
    """
    return torch.topk(depth.detach(), capacity, dim=-1, sorted=False).indices


def take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``x`` (B, G, S, 3) at indices ``idx`` (B, G, C) along dim 2 -> (B, G, C, 3)."""
    return torch.gather(x, 2, idx.unsqueeze(-1).expand(*idx.shape, x.shape[-1]))


def depth_weights(depth: torch.Tensor) -> torch.Tensor:
    """Share of each contact in its set, ``w_i = delta_i / sum_j delta_j``.

    Args:
        depth: (B, C) penetration depths (>= 0) of the C candidate contacts of each set.
    Returns:
        (B, C) weights (all zero for a set without contact).
    """
    total = depth.sum(-1, keepdim=True)
    return depth / (total + torch.finfo(depth.dtype).tiny)


def normal_force(depth: torch.Tensor, weight: torch.Tensor, normal_velocity: torch.Tensor,
                 stiffness: torch.Tensor, unload: torch.Tensor, unload_velocity: float, omega: float) -> torch.Tensor:
    """Depth-weighted hysteretic spring normal forces of one contact set.

    Args:
        depth: (B, C) penetration depths (>= 0).
        weight: (B, C) ``depth_weights(depth)``.
        normal_velocity: (B, C) normal velocity of each contact point (negative approaching).
        stiffness: broadcastable to (B, C), body-level stiffness k.
        unload: broadcastable to (B, C), unloading stiffness factor phi in [``UNLOAD_MIN``, 1].
        unload_velocity, omega: v_s (m/s) and omega_0 (rad/s) of ``restitution.loading``'s blend.
    Returns:
        (B, C) normal force magnitudes (>= 0: a factor phi + (1 - phi) s below zero, a negative
        phi's late in an impact's unloading, is cut off at zero)."""
    s = loading(depth, normal_velocity, unload_velocity, omega)
    return weight * stiffness * depth * (unload + (1.0 - unload) * s).clamp_min(0.0)


def friction_force(tangential_velocity: torch.Tensor, coulomb: torch.Tensor,
                   stick: torch.Tensor) -> torch.Tensor:
    """Coulomb friction with a one-substep stick limit (see the module docstring).

    Args:
        tangential_velocity: (..., 3) tangential velocity v_t of each contact point.
        coulomb: broadcastable to (...), Coulomb limit mu f_n (>= 0).
        stick: broadcastable to (...), c = w m_eff / h: the force per unit slip speed
            that stops the slip in one substep (>= 0).
    Returns:
        (..., 3) friction forces opposing the tangential velocity.
    """
    speed = torch.sqrt((tangential_velocity * tangential_velocity).sum(-1) + TINY)
    b = stick * speed
    # a c / (a^p + b^p)^(1/p) on numbers scaled by max(a, b), so float32 cannot overflow
    scale = torch.maximum(coulomb, b) + TINY
    den = (((coulomb / scale) ** SMOOTH_MIN_POWER + (b / scale) ** SMOOTH_MIN_POWER + TINY)
           ** (1.0 / SMOOTH_MIN_POWER)) * scale
    return -(coulomb * stick / den).unsqueeze(-1) * tangential_velocity


def _point_velocity(v: torch.Tensor, w: torch.Tensor, arm: torch.Tensor) -> torch.Tensor:
    return v + torch.linalg.cross(w.expand_as(arm), arm, dim=-1)


SLIP_EPS = 1e-3
"""Slip speed (m/s) below which a contact's effective mass fades to its all-direction bound."""


def _slip_direction(slip: torch.Tensor) -> torch.Tensor:
    """``t = v_t / sqrt(|v_t|^2 + SLIP_EPS^2)`` (..., 3): a unit vector while slipping, 0 at rest."""
    return slip / torch.sqrt((slip * slip).sum(-1, keepdim=True) + SLIP_EPS * SLIP_EPS)


def _inverse_mass(arm: torch.Tensor, t: torch.Tensor, inv_inertia_w: torch.Tensor,
                  inv_inertia_min: torch.Tensor) -> torch.Tensor:
    """Rotational part of 1 / m_i (see the module docstring) for arms (B, N, ..., 3).

    ``(r x t)^T I_w^-1 (r x t) + (1 - |t|^2) |r|^2 / I_min``: the effective mass
    along the slip while slipping, its lower bound over all directions at rest.

    Args:
        arm: (B, N, ..., 3) lever arms; t: ``_slip_direction`` of the tangential velocities alike.
        inv_inertia_w: (B, N, 3, 3) world-frame inverse inertia.
        inv_inertia_min: (N,) 1 / smallest principal moment.
    Returns:
        (B, N, ...) inverse-mass terms.
    """
    u = torch.linalg.cross(arm, t, dim=-1)
    shape = u.shape
    flat = u.reshape(shape[0], shape[1], -1, 3)
    along = (flat * small_matmul(flat, inv_inertia_w.transpose(-1, -2))).sum(-1).reshape(shape[:-1])
    rest = (1.0 - (t * t).sum(-1)) * (arm * arm).sum(-1)
    extra = rest.dim() - 2
    return along + rest * inv_inertia_min.reshape(-1, *([1] * extra))


def predicted_slip_change(fn: torch.Tensor, normal: torch.Tensor, arm: torch.Tensor, mass: torch.Tensor,
                          inv_inertia_w: torch.Tensor) -> torch.Tensor:
    """Rate of change (B, N, K, C, 3) of each contact point's tangential velocity that the normal
    forces of its body's static contacts give (the module docstring's predicted slip).

    Args:
        fn: (B, N, K, C) normal force magnitudes; normal, arm: (B, N, K, C, 3).
        mass: (N,); inv_inertia_w: (B, N, 3, 3) world-frame inverse inertia.
    Returns:
        ``(a + alpha x r_i)`` projected on each contact's tangent plane, with a = F_N / m and
        alpha = I_w^-1 T_N from the set's normal force F_N and torque T_N (both summed over K, C).
    """
    f = fn.unsqueeze(-1) * normal
    total_f = f.sum((2, 3))  # (B, N, 3)
    total_t = torch.linalg.cross(arm, f, dim=-1).sum((2, 3))
    alpha = small_matmul(total_t.unsqueeze(-2), inv_inertia_w.transpose(-1, -2)).squeeze(-2)  # (B, N, 3)
    acc = total_f / mass[:, None]
    dv = acc[:, :, None, None, :] + torch.linalg.cross(alpha[:, :, None, None, :].expand_as(arm), arm, dim=-1)
    return dv - (dv * normal).sum(-1, keepdim=True) * normal


def predicted_pair_slip_change(fn: torch.Tensor, normal: torch.Tensor, arm_a: torch.Tensor, arm_b: torch.Tensor,
                               mass_a: torch.Tensor, mass_b: torch.Tensor, inv_inertia_a: torch.Tensor,
                               inv_inertia_b: torch.Tensor) -> torch.Tensor:
    """``predicted_slip_change`` for body pairs: rate of change (B, P, C, 3) of each contact's
    relative tangential velocity (b's point minus a's) that the pair's normal forces give.

    Args:
        fn: (B, P, C) normal forces (on b along ``normal``, on a against it); normal, arm_a,
            arm_b: (B, P, C, 3); mass_a, mass_b: (P,); inv_inertia_a, inv_inertia_b: (B, P, 3, 3).
    Returns:
        ``F (1/m_a + 1/m_b) + alpha_b x r_b - alpha_a x r_a`` on each tangent plane, F the pair's
        normal force on b and alpha = I_w^-1 T from each body's normal torque T.
    """
    f = fn.unsqueeze(-1) * normal  # on b
    total_f = f.sum(2)  # (B, P, 3)
    t_a = torch.linalg.cross(arm_a, -f, dim=-1).sum(2)
    t_b = torch.linalg.cross(arm_b, f, dim=-1).sum(2)
    alpha_a = small_matmul(t_a.unsqueeze(-2), inv_inertia_a.transpose(-1, -2)).squeeze(-2)
    alpha_b = small_matmul(t_b.unsqueeze(-2), inv_inertia_b.transpose(-1, -2)).squeeze(-2)
    acc = total_f * (1.0 / mass_a + 1.0 / mass_b)[:, None]
    dv = (acc.unsqueeze(-2) + torch.linalg.cross(alpha_b.unsqueeze(-2).expand_as(arm_b), arm_b, dim=-1)
          - torch.linalg.cross(alpha_a.unsqueeze(-2).expand_as(arm_a), arm_a, dim=-1))
    return dv - (dv * normal).sum(-1, keepdim=True) * normal


def _pad_contacts(t: torch.Tensor, width: int) -> torch.Tensor:
    """A group's contacts (B, N, C, ...) padded with zeros (contacts of no depth) to ``width``."""
    if t.shape[2] == width:
        return t
    return torch.cat([t, t.new_zeros(*t.shape[:2], width - t.shape[2], *t.shape[3:])], 2)


def static_contact_wrench(world, state, spheres: torch.Tensor, h: float,
                          inv_inertia_w: torch.Tensor, rot: torch.Tensor | None = None):
    """Force and torque on every body from contacts with all static shapes.

    A box body against a static box: the static's edges meet the body's exact faces
    (``dejaview.sim.box_edges``); the body's spheres whose closest point on the static is on an
    edge or a corner are left out.

    Args:
        world: the World.
        state: current State, (B, N, ...).
        spheres: (B, N, S, 3) world sphere centres.
        h: integration substep (s), for the friction stick limit.
        inv_inertia_w: (B, N, 3, 3) world-frame inverse inertia of every body.
        rot: (B, N, 3, 3) world-from-body rotations, where the caller has them (the static box
            edges need them; else made from the state's orientations).
    Returns:
        force (B, N, 3), torque (B, N, 3) about each centre of mass.
    """
    if not world.statics:
        z = torch.zeros_like(state.position)
        return z, z
    radii, mask = world.radii, world.mask  # (N, S)
    arms_c = spheres - state.position.unsqueeze(-2)  # (B, N, S, 3)
    b, nb, s = spheres.shape[:3]
    cap = world.contact.max_static_contacts
    edges = any(world.box_bodies)
    if edges:
        is_box = torch.tensor(world.box_bodies, dtype=torch.bool, device=spheres.device)  # (N,)
        rot = quat_to_matrix(state.orientation) if rot is None else rot
        # a box body meets planes and static boxes with its corners: the packing's spheres and then
        # the 8 corner spheres (box_corners), each masked to the bodies it belongs to
        corner_c, corner_r = box_corners(world.box_half)  # (N, 8, 3), (N, 8)
        corner_arm = small_matmul(corner_c.expand(b, nb, 8, 3), rot.transpose(-1, -2))  # (B, N, 8, 3)
        corner_set = (torch.cat([spheres, state.position.unsqueeze(-2) + corner_arm], 2),
                      torch.cat([radii, corner_r], 1),
                      torch.cat([mask * ~is_box[:, None], is_box[:, None].expand(nb, 8).to(mask.dtype)], 1),
                      torch.cat([arms_c, corner_arm], 2))
    groups = []  # per group: depth (B, N, C), normal (B, N, C, 3), arm (B, N, C, 3), its static
    for k, shape in enumerate(world.statics):
        box_edges = edges and shape.kind == "box"
        pts, r, m, arm_c = corner_set if edges and shape.kind in CORNER_KINDS else (spheres, radii, mask, arms_c)
        keep = None
        if box_edges:  # a box body's corners off the static's faces give way to its edge points
            keep = ~(on_static_edge(shape, pts.detach()) & is_box[None, :, None])
        count = pts.shape[2]
        if count > cap:  # a static shape: per body its ``cap`` deepest spheres only
            d0, _ = shape.distance(pts.detach())
            d0 = torch.relu(r - d0) * m
            idx = deepest(d0 if keep is None else d0 * keep, cap)  # (B, N, C)
            pts, arm_c = take(pts, idx), take(arm_c, idx)
            r, m = r.expand(b, nb, count).gather(2, idx), m.expand(b, nb, count).gather(2, idx)
            keep = None if keep is None else keep.gather(2, idx)
        d, n = shape.distance(pts)  # (B, N, C), (B, N, C, 3)
        depth = torch.relu(r - d) * m
        if keep is not None:
            depth = torch.where(keep, depth, torch.zeros_like(depth))
        groups.append((depth, n, arm_c - n * r.unsqueeze(-1), k))
        if box_edges:
            groups.append((*static_edge_contacts(world, state, shape, rot, is_box, cap), k))
    width = max(g[0].shape[2] for g in groups)
    depth = torch.stack([_pad_contacts(g[0], width) for g in groups], 2)  # (B, N, K, C): K groups
    normal = torch.stack([_pad_contacts(g[1], width) for g in groups], 2)  # (B, N, K, C, 3)
    arm = torch.stack([_pad_contacts(g[2], width) for g in groups], 2)
    which = [g[3] for g in groups]
    v = state.linear_velocity[:, :, None, None, :]
    w = state.angular_velocity[:, :, None, None, :]
    vel = _point_velocity(v, w, arm)
    moving = [world.statics[k].velocity is not None for k in which]
    lines = ~is_box if edges else None
    if any(moving):  # relative to a moving static's own point there (dejaview.sim.motion)
        vel = vel - static_point_velocity([world.statics[k] for k in which], state.position, arm)
        # no roll stick against a moving static (line_contact: it holds a line on still geometry)
        on_moving = (depth[:, :, torch.tensor(moving, device=depth.device)] > 0).flatten(2).any(-1)  # (B, N)
        lines = ~on_moving if lines is None else lines & ~on_moving
    vn = (vel * normal).sum(-1)
    vt = vel - vn.unsqueeze(-1) * normal
    k, s = depth.shape[2:]
    m = world.mass  # (N,)
    omega = world.contact.frequency
    stiff = (m * omega ** 2)[None, :, None]  # (1, N, 1)
    unload_k, mu_k = world.unload_static[:, which], world.mu_static[:, which]  # (N, K)
    unload = unload_k[None, :, :, None].expand(b, nb, k, s).reshape(b, nb, k * s)
    mu = mu_k[None, :, :, None]
    if world.physics is not None:
        mu, unload, stiff = candidate_material(world.physics, mu, unload, stiff)
    flat_depth = depth.reshape(b, nb, k * s)
    weight = depth_weights(flat_depth)
    fn = normal_force(flat_depth, weight, vn.reshape(b, nb, k * s), stiff, unload,
                      world.contact.unload_velocity, omega).reshape(b, nb, k, s)
    vt = vt + h * predicted_slip_change(fn, normal, arm, m, inv_inertia_w)
    inv_mass = (1.0 / m)[:, None, None] + _inverse_mass(arm, _slip_direction(vt), inv_inertia_w,
                                                       world.inv_inertia_min)
    stick = weight.reshape(b, nb, k, s) / (inv_mass * h)
    ft = friction_force(vt, mu * fn, stick)
    fn = line_roll_stick(fn.reshape(b, nb, k * s), weight, arm.reshape(b, nb, k * s, 3),
                         normal.reshape(b, nb, k * s, 3), state.angular_velocity, m, inv_inertia_w,
                         roll_stop_time(h, omega), lines).reshape(b, nb, k, s)
    force = fn.unsqueeze(-1) * normal + ft  # (B, N, K, C, 3)
    torque = torch.linalg.cross(arm, force, dim=-1)
    return force.sum((2, 3)), torque.sum((2, 3))


def pair_contact_wrench(world, state, spheres: torch.Tensor, h: float, inv_inertia_w: torch.Tensor,
                        pair_ids=None):
    """Force and torque on every body from contacts between movable bodies.

    A pair meets sphere against sphere, or, where one body is a box (``World.pair_surface``), the
    other body's spheres against that box's exact surface (the module docstring, "Body pairs
    against a box").

    Args:
        world: the World.
        state: current State.
        spheres: (B, N, S, 3) world sphere centres.
        h: integration substep (s).
        inv_inertia_w: (B, N, 3, 3) world-frame inverse inertia of every body.
        pair_ids: indices into ``world.pairs`` to evaluate (None: all). The
            caller's broad phase passes only pairs whose bounding spheres overlap.
    Returns:
        force (B, N, 3), torque (B, N, 3).
    """
    force = torch.zeros_like(state.position)
    torque = torch.zeros_like(state.position)
    n_pairs = world.pairs.shape[0]
    if n_pairs == 0:
        return force, torque
    surface = world.pair_surface
    if all(side < 0 for side in surface):  # no box: every pair sphere against sphere
        groups = [(-1, pair_ids)]
    else:  # a constant split (World's), so no data-dependent branch under transforms
        ids = range(n_pairs) if pair_ids is None else [int(k) for k in pair_ids.tolist()]
        groups = []
        for side in (-1, 0, 1):
            chosen = [k for k in ids if surface[k] == side]
            if chosen:
                groups.append((side, torch.tensor(chosen, dtype=torch.int64, device=world.pairs.device)))
    rot = None
    n_bodies = state.position.shape[1]
    for side, sel in groups:
        pick = (lambda t: t) if sel is None else (lambda t: t[sel])  # noqa: E731
        pairs = pick(world.pairs)
        if pairs.shape[0] == 0:
            continue
        ia, ib = pairs[:, 0], pairs[:, 1]
        if side < 0:
            cand = _sphere_pair_candidates(world, spheres, ia, ib)
        else:
            if rot is None:
                rot = quat_to_matrix(state.orientation)
            cand = _surface_candidates(world, state, spheres, rot, ia, ib, side)
        fb_tot, ta, tb = _pair_law(world, state, cand, ia, ib, pick(world.mu_pair), pick(world.unload_pair),
                                   pick(world.mass_pair), h, inv_inertia_w)
        # scatter to the bodies through one-hot incidence matrices (P, N), not ``index_add``:
        # inductor (torch 2.13) miscompiled the index_add of a training graph of two substeps
        # (forward values off by 1e-3 at the first body-pair contact; tests/sim/test_compile.py)
        one_a = torch.nn.functional.one_hot(ia, n_bodies).to(fb_tot.dtype)
        one_b = torch.nn.functional.one_hot(ib, n_bodies).to(fb_tot.dtype)
        force = force + torch.einsum("bpk,pn->bnk", fb_tot, one_b - one_a)
        torque = torque + torch.einsum("bpk,pn->bnk", ta, one_a) + torch.einsum("bpk,pn->bnk", tb, one_b)
    return force, torque


def _sphere_pair_candidates(world, spheres: torch.Tensor, ia: torch.Tensor, ib: torch.Tensor):
    """Sphere pairs of body pairs (ia, ib) (P,): centres pa, pb (B, P, C, 3), radii ra, rb and
    mask (B, P, C); every sphere of a against every sphere of b, or the ``max_pair_contacts``
    deepest of them."""
    pa, pb = spheres[:, ia], spheres[:, ib]  # (B, P, S, 3)
    b, p, s = pa.shape[:3]
    ra, rb = world.radii[ia].expand(b, p, s), world.radii[ib].expand(b, p, s)  # (B, P, S)
    ma, mb = world.mask[ia].expand(b, p, s), world.mask[ib].expand(b, p, s)
    cap = world.contact.max_pair_contacts
    if s * s > cap:  # the ``cap`` deepest sphere pairs of each body pair
        pad, pbd = pa.detach(), pb.detach()
        dist0 = torch.linalg.vector_norm(pbd.unsqueeze(-3) - pad.unsqueeze(-2), dim=-1)  # (B, P, S, S)
        depth0 = (torch.relu(ra.unsqueeze(-1) + rb.unsqueeze(-2) - dist0)
                  * (ma.unsqueeze(-1) * mb.unsqueeze(-2)))
        idx = deepest(depth0.reshape(b, p, s * s), cap)  # (B, P, C)
        i, j = idx // s, idx % s
        pa, pb = take(pa, i), take(pb, j)
        ra, rb, ma, mb = ra.gather(2, i), rb.gather(2, j), ma.gather(2, i), mb.gather(2, j)
    else:  # every sphere of a against every sphere of b, flattened to C = S * S
        pa = pa.unsqueeze(-2).expand(b, p, s, s, 3).reshape(b, p, s * s, 3)
        pb = pb.unsqueeze(-3).expand(b, p, s, s, 3).reshape(b, p, s * s, 3)
        ra, ma = (t.unsqueeze(-1).expand(b, p, s, s).reshape(b, p, -1) for t in (ra, ma))
        rb, mb = (t.unsqueeze(-2).expand(b, p, s, s).reshape(b, p, -1) for t in (rb, mb))
    return pa, pb, ra, rb, ma * mb


def box_partner(points: torch.Tensor, centre: torch.Tensor, rot: torch.Tensor,
                half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Boxes' surfaces as spheres partnering world points: centres (B, P, S, 3) and radii (B, P, S).

    Outside a box: its closest point to the point, radius 0, ``x + R clamp(R^T (p - x), -half,
    half)``. Inside (a sphere's centre that has crossed the surface: a penetration deeper than its
    radius): on the normal of the nearest face, ``deep = 1 + |half|`` behind it, radius ``deep``.
    Either way |p - q| - radius is the box's signed distance at p and (p - q) / |p - q| its
    outward normal, so the sphere-pair law pushes the point out through the nearest face.

    Args:
        points: (B, P, S, 3); centre: (B, P, 3) box centres; rot: (B, P, 3, 3) world-from-box
            rotations; half: (P, 3) half extents.
    """
    local = small_matmul(points - centre.unsqueeze(-2), rot)  # rows R^T (p - x)
    lim = half.unsqueeze(-2)  # (P, 1, 3)
    over = local.abs() - lim
    outside = (over > 0).any(-1)  # (B, P, S)
    clamped = torch.maximum(torch.minimum(local, lim), -lim)
    deep = 1.0 + torch.linalg.vector_norm(half, dim=-1)[:, None]  # (P, 1)
    face = torch.nn.functional.one_hot(over.detach().argmax(-1), 3).to(torch.bool)  # nearest face
    sign = torch.where(local.detach() < 0, -1.0, 1.0).to(local.dtype)
    behind = torch.where(face, sign * (lim - deep.unsqueeze(-1)), local)
    inner = torch.where(outside.unsqueeze(-1), clamped, behind)
    radius = torch.where(outside, torch.zeros_like(over[..., 0]), deep.expand_as(over[..., 0]))
    return centre.unsqueeze(-2) + small_matmul(inner, rot.transpose(-1, -2)), radius


def _surface_candidates(world, state, spheres: torch.Tensor, rot: torch.Tensor, ia: torch.Tensor,
                        ib: torch.Tensor, side: int):
    """Body pairs (ia, ib) (P,) whose body ``side`` (0: a, 1: b) is a box: the other body's spheres,
    each with the box's surface as its partner (``box_partner``), as ``_sphere_pair_candidates``
    returns them, the ``max_pair_contacts`` deepest where there are more."""
    box, other = (ia, ib) if side == 0 else (ib, ia)
    p_o = spheres[:, other]  # (B, P, S, 3)
    b, p, s = p_o.shape[:3]
    r_o, m_o = world.radii[other].expand(b, p, s), world.mask[other].expand(b, p, s)
    cap = world.contact.max_pair_contacts
    if s > cap:
        q0, rq0 = box_partner(p_o.detach(), state.position[:, box].detach(), rot[:, box].detach(),
                              world.box_half[box])
        depth0 = torch.relu(r_o + rq0 - torch.linalg.vector_norm(p_o.detach() - q0, dim=-1)) * m_o
        idx = deepest(depth0, cap)
        p_o, r_o, m_o = take(p_o, idx), r_o.gather(2, idx), m_o.gather(2, idx)
    q, rq = box_partner(p_o, state.position[:, box], rot[:, box], world.box_half[box])
    if side == 0:
        return q, p_o, rq, r_o, m_o
    return p_o, q, r_o, rq, m_o


def _pair_law(world, state, cand, ia: torch.Tensor, ib: torch.Tensor, mu_p: torch.Tensor,
              unload_p: torch.Tensor, mass_p: torch.Tensor, h: float, inv_inertia_w: torch.Tensor):
    """The contact law on candidates (pa, pb, ra, rb, mask) of body pairs (ia, ib) (P,): the
    force on b (B, P, 3) (minus it on a) and the torques on a and on b (B, P, 3)."""
    pa, pb, ra, rb, mask = cand
    diff = pb - pa  # (B, P, C, 3) from a's sphere to b's
    dist = torch.sqrt((diff * diff).sum(-1) + NORMAL_EPS2)
    n = diff / dist.unsqueeze(-1)
    depth = torch.relu(ra + rb - dist) * mask  # (B, P, C)
    point = pa + n * ra.unsqueeze(-1)  # contact point on a's sphere
    xa = state.position[:, ia].unsqueeze(-2)  # (B, P, 1, 3)
    xb = state.position[:, ib].unsqueeze(-2)
    arm_a, arm_b = point - xa, point - xb
    va = _point_velocity(state.linear_velocity[:, ia].unsqueeze(-2),
                         state.angular_velocity[:, ia].unsqueeze(-2), arm_a)
    vb = _point_velocity(state.linear_velocity[:, ib].unsqueeze(-2),
                         state.angular_velocity[:, ib].unsqueeze(-2), arm_b)
    vrel = vb - va
    vn = (vrel * n).sum(-1)  # separating > 0
    vt = vrel - vn.unsqueeze(-1) * n
    omega = world.contact.frequency
    stiff = (mass_p * omega ** 2)[None, :, None]
    unload = unload_p[None, :, None]
    mu = mu_p[None, :, None]
    if world.physics is not None:
        mu, unload, stiff = candidate_material(world.physics, mu, unload, stiff)
    weight = depth_weights(depth)
    fn = normal_force(depth, weight, vn, stiff, unload, world.contact.unload_velocity, omega)
    vt = vt + h * predicted_pair_slip_change(fn, n, arm_a, arm_b, world.mass[ia], world.mass[ib],
                                             inv_inertia_w[:, ia], inv_inertia_w[:, ib])
    inv_i = world.inv_inertia_min
    t = _slip_direction(vt)  # once for both bodies of each pair
    inv_mass = ((1.0 / world.mass[ia] + 1.0 / world.mass[ib])[:, None]
                + _inverse_mass(arm_a, t, inv_inertia_w[:, ia], inv_i[ia])
                + _inverse_mass(arm_b, t, inv_inertia_w[:, ib], inv_i[ib]))
    stick = weight / (inv_mass * h)
    ft = friction_force(vt, mu * fn, stick)
    f_b = fn.unsqueeze(-1) * n + ft  # on b, (B, P, C, 3)
    return (f_b.sum(2), torch.linalg.cross(arm_a, -f_b, dim=-1).sum(2),
            torch.linalg.cross(arm_b, f_b, dim=-1).sum(2))


def pair_bounding_overlap(world, state, margin: float = 0.0) -> torch.Tensor:
    """Broad phase: which body pairs' bounding spheres overlap in any batch element.

    Returns:
        (P,) bool.
    """
    ia, ib = world.pairs[:, 0], world.pairs[:, 1]
    d = torch.linalg.vector_norm(state.position[:, ia] - state.position[:, ib], dim=-1)  # (B, P)
    return (d < world.bound[ia] + world.bound[ib] + margin).any(0)
