"""The simulator against closed-form physics."""

import numpy as np
import pytest
import torch

from dejaview.sim import StaticShape, rollout
from tests.sim.conftest import ball_body, box_body, make_world

G = 9.81


def _needs(engine: str) -> None:
    """Skip a native case where the native extension does not build (no compiler)."""
    if engine == "native":
        from dejaview.sim import native

        if not native.available():
            pytest.skip("the native extension does not build here")


def _weightless(bodies, statics, mu: float = 0.5, e: float = 0.3):
    """A world without gravity (an impact alone acts), dt 2 ms in 2 substeps."""
    from dejaview.sim.world import World

    return World.build(bodies, statics, gravity=(0.0, 0.0, 0.0), dt=0.002, substeps=2, friction=mu, restitution=e)


def _heavy_ball(mu: float, e: float):
    """A ball of 1 m radius and 10 t: a curved surface that a body pair meets and that stays."""
    return ball_body("big", radius=1.0, mass=1e4, friction=mu, restitution=e)


def _heavy_box(centers, radii, e: float):
    """A box of 0.2 x 0.15 x 0.1 m and 10 t (so it stays), packed with spheres ``centers`` (S, 3)
    and ``radii`` (S,), that other bodies meet on its exact surface (``BodySpec.box_half``)."""
    from dejaview.sim.world import BodySpec

    size, heavy = (0.2, 0.15, 0.1), 1e4
    a, b, c = size
    inertia = heavy / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    return BodySpec("box", heavy, inertia, np.zeros(3), np.asarray(centers), np.asarray(radii), restitution=e,
                    box_half=tuple(0.5 * v for v in size))


def test_free_fall_matches_analytic_within_integrator_error():
    """Semi-implicit Euler: x_n = x0 + v0 t + g t^2 / 2 + g t h / 2 exactly (h the substep)."""
    world = make_world([ball_body()], [], dt=0.002, substeps=2)
    v0 = torch.tensor([0.5, -0.2, 2.0], dtype=torch.float64)
    state = world.state([[0.0, 0.0, 1.0]], linear_velocity=[v0.tolist()])
    steps = 250
    traj = rollout(world, state, steps=steps)
    t = steps * world.dt
    h = world.dt / world.substeps
    g = world.gravity
    analytic = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) + v0 * t + 0.5 * g * t * t
    known_error = 0.5 * g * t * h
    got = traj.final.position[0, 0]
    assert torch.allclose(got, analytic + known_error, atol=1e-9)
    assert (got - analytic).abs().max() <= 0.5 * G * t * h + 1e-9
    assert torch.allclose(traj.final.linear_velocity[0, 0], v0 + g * t, atol=1e-9)


def test_box_sliding_stops_at_v2_over_2_mu_g():
    mu, v0 = 0.4, 2.0
    box = box_body(friction=mu)
    floor = StaticShape.make("floor", "plane", friction=mu)
    world = make_world([box], [floor], dt=0.002, substeps=2, friction=mu)
    state = world.state([[0.0, 0.0, 0.05]], linear_velocity=[[v0, 0.0, 0.0]])
    traj = rollout(world, state, steps=400)
    x = traj.states.position[:, 0, 0, 0]
    speed = traj.states.linear_velocity[:, 0, 0, 0]
    assert speed[-1].abs() < 1e-3
    expected = v0 ** 2 / (2 * mu * G)
    assert abs(x[-1].item() - expected) / expected < 0.03


@pytest.mark.parametrize("e", [0.5, 0.8])
def test_ball_rebounds_to_e_squared_h(e):
    r, h0 = 0.05, 0.5
    world = make_world([ball_body(radius=r, restitution=e)],
                       [StaticShape.make("floor", "plane", restitution=e)], dt=0.002, substeps=2)
    traj = rollout(world, world.state([[0.0, 0.0, h0 + r]]), steps=600)
    z = traj.states.position[:, 0, 0, 2].numpy() - r
    first_contact = int(np.argmax(z < 0))
    bottom = first_contact + int(np.argmin(z[first_contact:first_contact + 50]))
    rebound = z[bottom:].max()
    assert abs(rebound - e * e * h0) / (e * e * h0) < 0.10


def _thrown_at_the_floor(world, r: float, speed: float, n: int, engine: str):
    """n balls of radius r thrown straight down at ``speed`` from heights spread over one substep's
    travel above the floor (so each impact's deepest point falls elsewhere in its substep), 40 steps."""
    heights = r + 0.01 + torch.linspace(0.0, speed * world.dt / world.substeps, n, dtype=torch.float64)
    position = torch.zeros(n, 1, 3, dtype=torch.float64)
    position[:, 0, 2] = heights
    velocity = torch.zeros(n, 1, 3, dtype=torch.float64)
    velocity[:, 0, 2] = -speed
    return rollout(world, world.state(position, linear_velocity=velocity), steps=40, engine=engine)


@pytest.mark.parametrize("engine", ["native", "torch"])
@pytest.mark.parametrize("e", [0.2, 0.4])
def test_a_balls_restitution_does_not_depend_on_where_in_its_substep_it_lands(engine, e):
    """Balls thrown head-on at the floor at 3 m/s without gravity from 32 heights spread over one
    substep's travel (3 mm): each rebounds with the restitution the scene gives, within 0.01, and
    all within 0.004 of each other (measured 0.0014 and 0.0024 for e = 0.2 and 0.4). The
    loading-to-unloading blend spans a part of the impact's phase (``restitution.loading``); over
    v_s = 1 cm/s alone, crossed within one substep, the rebound was a sawtooth in the landing's
    phase: 0.192-0.296 for e = 0.2 and 0.395-0.447 for e = 0.4 (measured when written)."""
    _needs(engine)
    r, speed = 0.05, 3.0
    world = _weightless([ball_body(radius=r, restitution=e)], [StaticShape.make("floor", "plane", restitution=e)],
                        mu=0.5, e=e)
    traj = _thrown_at_the_floor(world, r, speed, 32, engine)
    rebound = traj.final.linear_velocity[:, 0, 2].numpy() / speed
    assert np.all(traj.final.position[:, 0, 2].numpy() > r), "a ball still touches the floor"
    assert rebound.max() - rebound.min() < 0.004, rebound
    assert np.abs(rebound - e).max() < 0.01, rebound


@pytest.mark.parametrize("engine", ["native", "torch"])
def test_a_restitution_below_the_blends_own_is_reached(engine):
    """With phi >= 0 every restitution up to 0.111 rebounded with 0.121 (the blend's own: at the
    deepest point it still holds sigmoid(-beta) of the loading stiffness). Below it phi goes
    negative, down to ``restitution.UNLOAD_MIN``, and the force is cut off where it would pull.
    Balls thrown head-on at the floor at 3 m/s without gravity from 16 heights over one substep's
    travel: measured 0.054, 0.059, 0.090, 0.110 for e = 0, 0.05, 0.08, 0.1 (the calibration's
    0.045, 0.05, 0.08, 0.1 are for v_s = 0: the blend's few mm/s widen it at a slow impact), each
    within 0.0007 over the heights; with gravity at 3 m/s e = 0 rebounds with 0.044."""
    _needs(engine)
    r, speed, n = 0.05, 3.0, 16
    out = {}
    for e, g in [(0.0, 0.0), (0.05, 0.0), (0.08, 0.0), (0.1, 0.0), (0.0, G)]:
        from dejaview.sim.world import World

        world = World.build([ball_body(radius=r, restitution=e)], [StaticShape.make("floor", "plane", restitution=e)],
                            gravity=(0.0, 0.0, -g), dt=0.002, substeps=2, friction=0.5, restitution=e)
        traj = _thrown_at_the_floor(world, r, speed, n, engine)
        rebound = traj.states.linear_velocity[:, :, 0, 2].max(0).values.numpy() / speed
        assert rebound.max() - rebound.min() < 0.003, (e, g, rebound)
        out[e, g] = float(rebound.mean())
    assert out[0.0, 0.0] < 0.065 and out[0.0, G] < 0.055, out
    assert out[0.0, 0.0] < out[0.05, 0.0] < out[0.08, 0.0] < out[0.1, 0.0] < 0.115, out
    assert abs(out[0.08, 0.0] - 0.08) < 0.015 and abs(out[0.1, 0.0] - 0.1) < 0.015, out


@pytest.mark.parametrize("e", [0.2, 0.0])
def test_box_resting_on_table_stays_and_gains_no_energy(e):
    """Also at restitution 0, whose unloading factor is the least (``restitution.UNLOAD_MIN``, below
    zero): the blend at rest keeps the factor above zero, so the box rests (0.6 mm deep, 0.45 mm at
    e = 0.2) and does not sink."""
    top = StaticShape.make("table", "box", position=(0.0, 0.0, 0.70), half=(0.6, 0.4, 0.05), restitution=e)
    box = box_body(mass=2.0)
    world = make_world([box], [top], dt=0.002, substeps=2, restitution=e)
    start = [[0.1, -0.05, 0.75 + 0.05]]
    state = world.state(start)
    traj = rollout(world, state, steps=1500)  # 3 s
    pos = traj.states.position[:, 0, 0]
    drift = (pos - pos[0]).norm(dim=-1).max().item()
    assert drift < 1e-3
    m = world.mass[0]
    v = traj.states.linear_velocity[:, 0, 0]
    w = traj.states.angular_velocity[:, 0, 0]
    inertia = world.inertia[0]
    energy = 0.5 * m * (v * v).sum(-1) + 0.5 * (w * (w @ inertia)).sum(-1) + m * G * pos[:, 2]
    assert (energy - energy[0]).max().item() < 1e-6
    # and it is at rest at the end
    assert v[-1].norm() < 1e-3 and w[-1].norm() < 1e-2


def _sticking_impact(inertia_w: np.ndarray, mass: float, arm: np.ndarray, e: float, speed: float):
    """Rigid-body impact of a body falling at ``speed`` without spin onto a floor (normal +z) at the
    point ``arm`` (3,) from its centre of mass, the point leaving without slip and with e times its
    normal speed (Newton): impulse P from the point's Delassus matrix K, P = K^-1 du. Returns the
    changes of the linear and angular velocity, and |P_t| / P_n (the friction it needs)."""
    cross = lambda v: np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])  # noqa: E731
    inv_i = np.linalg.inv(inertia_w)
    K = np.eye(3) / mass - cross(arm) @ inv_i @ cross(arm)
    P = np.linalg.solve(K, np.array([0.0, 0.0, (1.0 + e) * speed]))
    return P / mass, inv_i @ np.cross(arm, P), float(np.hypot(P[0], P[1]) / P[2])


def _tilted_box(tilt: float):
    """A box of 0.2 x 0.15 x 0.1 m and 1 kg (mu 0.5, e 0.3) turned by ``tilt`` degrees about y, so
    its edge along y is lowest: (body, mass, inertia, mu, e, centers, radii, rot, low, q) with
    ``low`` (S,) each sphere's lowest point above the centre and ``q`` the orientation (1, 4)."""
    from dejaview.geometry.box_spheres import box_spheres
    from dejaview.sim.world import BodySpec

    size, mass, mu, e = (0.2, 0.15, 0.1), 1.0, 0.5, 0.3
    centers, radii = box_spheres(size)
    a, b, c = size
    inertia = mass / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    body = BodySpec("box", mass, inertia, np.zeros(3), centers, radii, friction=mu, restitution=e)
    t = np.radians(tilt)
    rot = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])  # about y
    low = (centers @ rot.T)[:, 2] - radii
    return body, mass, inertia, mu, e, centers, radii, rot, low, [[np.cos(t / 2), 0.0, np.sin(t / 2), 0.0]]


@pytest.mark.parametrize("engine", ["native", "torch"])
@pytest.mark.parametrize("tilt", [35.0, 40.0])
@pytest.mark.parametrize("surface", ["floor", "heavy ball"])
def test_box_landing_on_an_edge_leaves_it_without_slip_like_a_rigid_box(engine, tilt, surface):
    """A box landing on an edge at 1.4 m/s, where Coulomb friction (mu 0.5) can hold the edge (the
    rigid impact needs |P_t| / P_n of 0.37 and 0.31): the edge leaves without slip and the box
    with the rigid impact's velocities. On the floor (a static shape) and on the top of a ball of
    1 m radius and 10 t (a body pair), without gravity (the penalty contact lasts 25 ms, and gravity
    would add 13 % to its impulse where a rigid impact is instantaneous). The friction
    acts on the slip the substep would end with (``dejaview.sim.contacts``, "predicted slip"); on
    the slip at its start it lagged one substep behind the impact's normal force, the edge left
    sliding at 0.30-0.40 m/s and the box spun 40 % faster than the rigid box (on either surface).
    The native cases are skipped where the native extension does not build (no compiler).
    """
    _needs(engine)
    body, mass, inertia, mu, e, centers, radii, rot, low, q = _tilted_box(tilt)
    speed = np.sqrt(2 * G * 0.1)
    if surface == "floor":
        world = _weightless([body], [StaticShape.make("floor", "plane", friction=mu, restitution=e)], mu, e)
        state = world.state([[0.0, 0.0, 0.01 - low.min()]], orientation=q, linear_velocity=[[0.0, 0.0, -speed]])
    else:
        world = _weightless([body, _heavy_ball(mu, e)], [], mu, e)
        state = world.state([[0.0, 0.0, 0.01 - low.min()], [0.0, 0.0, -1.0]], orientation=q + [[1.0, 0, 0, 0]],
                            linear_velocity=[[0.0, 0.0, -speed], [0.0, 0.0, 0.0]])
    traj = rollout(world, state, steps=40, engine=engine)
    k = int(np.argmin(low))  # an edge sphere (the edge along y touches all along)
    arm = rot @ centers[k] - np.array([0.0, 0.0, radii[k]])
    arm[1] = 0.0
    dv, dw, needed = _sticking_impact(rot @ inertia @ rot.T, mass, arm, e, speed)
    assert needed < mu
    z = traj.states.position[:, 0, 0, 2].numpy()
    touch = int(np.argmax(z + low.min() < 0.0))
    after = touch + 20  # 40 ms on: the impact (with its slow unloading, about 25 ms) is over
    v = traj.states.linear_velocity[after, 0, 0].numpy()
    w = traj.states.angular_velocity[after, 0, 0].numpy()
    assert abs(v[0] - dv[0]) < 0.05 * abs(dv[0])
    assert abs(w[1] - dw[1]) < 0.1 * abs(dw[1])
    slip = v[0] + w[1] * arm[2]  # the edge's velocity along x
    assert abs(slip) < 0.1  # 7 % of the impact speed (measured 0.01-0.07; 0.31-0.40 before)


@pytest.mark.parametrize("engine", ["native", "torch"])
@pytest.mark.parametrize("tilt", [35.0, 40.0])
def test_a_box_landing_on_an_edge_while_sliding_along_it_does_not_roll_over_the_edge_line(engine, tilt):
    """The box above lands on its edge (along y) while sliding along it at 0.2 m/s, without gravity.
    Friction at the edge stops that slide; its force acts 5-9 cm below the centre and so would
    roll the box about x, lifting one end of the edge and pressing the other. A rigid edge's end
    forces hold that roll within the impact (MuJoCo: the box-thrown row of docs/physics-fidelity.md,
    roll within 0.4 deg after its edge landing); DejaView's normal forces, springs on depth, resisted
    it only as the ends sank and lifted, and the box left rolling at 0.65-0.77 rad/s about x. The
    roll stick of a line contact (``dejaview.sim.line_contact``) holds it: measured 0.09-0.15
    rad/s. The pitch (about y) and the rebound are the rigid impact's as in the test above. The
    native cases are skipped where the native extension does not build (no compiler)."""
    _needs(engine)
    body, mass, inertia, mu, e, centers, radii, rot, low, q = _tilted_box(tilt)
    speed = np.sqrt(2 * G * 0.1)
    world = _weightless([body], [StaticShape.make("floor", "plane", friction=mu, restitution=e)], mu, e)
    state = world.state([[0.0, 0.0, 0.01 - low.min()]], orientation=q, linear_velocity=[[0.0, 0.2, -speed]])
    traj = rollout(world, state, steps=60, engine=engine)
    z = traj.states.position[:, 0, 0, 2].numpy()
    touch = int(np.argmax(z + low.min() < 0.0))
    w = traj.states.angular_velocity[touch + 20:, 0, 0].numpy()  # the impact is over, the box in flight
    assert np.abs(w[:, 0]).max() < 0.25  # rad/s about x (0.65-0.77 without the roll stick)
    k = int(np.argmin(low))
    arm = rot @ centers[k] - np.array([0.0, 0.0, radii[k]])
    arm[1] = 0.0
    dv, dw, _ = _sticking_impact(rot @ inertia @ rot.T, mass, arm, e, speed)
    assert abs(w[0, 1] - dw[1]) < 0.1 * abs(dw[1])


@pytest.mark.parametrize("engine", ["native", "torch"])
@pytest.mark.parametrize("static", ["plane", "box"])
def test_a_box_body_meets_the_floor_with_its_exact_corner(engine, static):
    """A box body (``box_half``) tilted so that one corner is lowest, that corner 0.5 mm into a
    frictionless floor (a plane, or a static box's top face), without gravity: its packing's spheres
    are all clear of the floor (the spheres round the corner off by centimetres), and its corner
    (``dejaview.sim.box_edges.box_corners``) takes the impact: one step later the box moves up and
    turns as an upward push at that corner turns it, I_w dw = c x m dv."""
    _needs(engine)
    from dejaview.sim.box_edges import BOX_CORNER_RADIUS
    from dejaview.sim.rotation import quat_to_matrix, rotvec_to_quat

    half = np.array([0.1, 0.075, 0.05])
    body = box_body("box", box_half=tuple(half), friction=0.0, restitution=0.3)
    floor = (StaticShape.make("floor", "plane", friction=0.0) if static == "plane" else
             StaticShape.make("floor", "box", position=(0.0, 0.0, -0.5), half=(1.0, 1.0, 0.5), friction=0.0))
    world = _weightless([body], [floor], mu=0.0)
    q = rotvec_to_quat(torch.tensor([0.4, -0.3, 0.2], dtype=torch.float64))
    rot = quat_to_matrix(q).numpy()
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    r = BOX_CORNER_RADIUS
    corner = signs * (half - r) @ rot.T  # corner spheres' centres from the body's centre
    k = int(np.argmin(corner[:, 2]))
    z = -(corner[k, 2] - r) - 5e-4
    spheres = world.centers[0].numpy() @ rot.T
    assert (z + spheres[:, 2] - world.radii[0].numpy()).min() > 0.005  # the packing is clear of the floor
    state = world.state([[0.0, 0.0, z]], orientation=q.reshape(1, 4))
    traj = rollout(world, state, steps=1, engine=engine)
    dv = traj.final.linear_velocity[0, 0].numpy()
    dw = traj.final.angular_velocity[0, 0].numpy()
    assert dv[2] > 0.01 and np.abs(dv[:2]).max() < 1e-12 * dv[2] + 1e-15
    inertia_w = rot @ world.inertia[0].numpy() @ rot.T
    push = np.cross(corner[k] - [0.0, 0.0, r], world.mass[0].item() * dv)
    assert np.linalg.norm(inertia_w @ dw - push) < 0.02 * np.linalg.norm(push), (inertia_w @ dw, push)


def _corner_bounce(box_body: bool):
    """box-tumble-2's start (bench/crossengine.py): a box of 0.2 x 0.15 x 0.1 m and 1 kg thrown onto
    the floor, bouncing over corners and edges for 0.6 s: (world, state). ``box_body``: the scene's
    primitive box (its corners meet the floor, ``dejaview.sim.box_edges``), else the same box as a
    packing of spheres without ``box_half`` (as a mesh body: the roll stick of a line contact acts)."""
    from dejaview.scene import Scene
    from dejaview.sim.build import initial_state
    from dejaview.sim.world import World
    from tests.losses.helpers import axis_angle_quat

    q = " ".join(f"{v:.17g}" for v in axis_angle_quat((1.0, 2.0, 0.0), np.radians(30.0)).tolist())
    scene = Scene.from_string(f"""<scene version="1" name="corners" gravity="0 0 -9.81">
  <simulation dt="0.002" duration="1.0" friction="0.5" restitution="0.3"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
  <object id="box" shape="box" size="0.2 0.15 0.1" mass="1.0"><pose position="1.0 0.6 0.4" orientation="{q}"/>
    <velocity linear="0.3 -0.6 0.5" angular="2.0 1.0 3.0"/></object>
</scene>""")
    world = World.from_scene(scene)
    # a scene with a box body takes 4 substeps at the stiffness of 2 (bounds.BOX_BODY_SUBSTEPS)
    assert world.substeps == 4 and world.contact.frequency == 250.0 and world.box_bodies == (True,)
    if not box_body:
        body = _tilted_box(0.0)[0]
        world = World.build([body], list(world.statics), dt=0.002, substeps=2, steps=500)
    return world, initial_state(world, scene)


def _ends_at_substeps(world, state, substeps) -> np.ndarray:
    """The centre (3,) at 1.0 s with ``substeps`` per 2 ms step (the same contact stiffness)."""
    w = world.with_substeps(substeps)
    with torch.no_grad():
        traj = rollout(w, state, steps=500, engine="native")
    return traj.final.position[0, 0].numpy()


def test_a_packed_box_bouncing_over_corners_ends_where_it_ends_at_finer_substeps():
    """box-tumble-2's start with the box as a packing of spheres (the roll stick of a line contact
    acts on its edges): at 1.0 s its centre at 2 and at 8 substeps per 2 ms step is within 1 cm of
    where 32 substeps put it: measured 0.25 and 0.17 cm. While the roll stick stopped the roll
    within one substep rather than within the contact's time
    (``dejaview.sim.line_contact.roll_stop_time``), more substeps held it harder and the end moved
    41.9 and 31.2 cm. Native engine (the torch engine agrees with it:
    tests/sim/test_native_gradients.py)."""
    _needs("native")
    world, state = _corner_bounce(box_body=False)
    fine = _ends_at_substeps(world, state, 32)
    assert np.linalg.norm(fine[:2] - [1.0, 0.6]) > 0.2  # it went somewhere: the test is not of a box at rest
    for substeps in (2, 8):
        assert np.linalg.norm(_ends_at_substeps(world, state, substeps) - fine) < 0.01, substeps


def test_a_box_on_its_corners_bouncing_over_them_converges_with_the_substeps():
    """The same start with the primitive box, whose corners meet the floor
    (``dejaview.sim.box_edges``): its end at 2, 4, 8 and 16 substeps is 1.18, 2.40, 0.66 and
    0.17 cm from 32 substeps'. A corner is a point carrying the whole body spring (its stiffness
    m omega_0^2 acts about a lever of 12 cm, so the impact's own frequency is about 2.6 omega_0:
    2 substeps resolve it less finely than a face's: a scene with a box body takes 4 by default,
    ``bounds.BOX_BODY_SUBSTEPS``), and where the box tips over an edge
    at 0.4-0.7 s it amplifies the first impact's difference; a 1 mm nudge of the start moves the
    end 1 mm. So this checks convergence, within 2.5 cm at every step and 0.5 cm at 16."""
    _needs("native")
    world, state = _corner_bounce(box_body=True)
    fine = _ends_at_substeps(world, state, 32)
    assert np.linalg.norm(fine[:2] - [1.0, 0.6]) > 0.2
    gaps = [float(np.linalg.norm(_ends_at_substeps(world, state, k) - fine)) for k in (2, 4, 8, 16)]
    assert max(gaps) < 0.025 and gaps[-1] < 0.005, gaps


@pytest.mark.parametrize("engine", ["native", "torch"])
@pytest.mark.parametrize("surface", ["wall", "heavy ball"])
def test_ball_striking_a_surface_obliquely_leaves_it_as_a_rigid_sticking_impact(engine, surface):
    """A ball (5 cm, solid) strikes a wall at 1.71 m/s with 0.68 m/s along it, without gravity:
    Coulomb friction (mu 0.5) can stop the contact point's slip within the impact (it needs
    |P_t| / P_n = 0.09), so a rigid ball leaves with 5/7 of its speed along the wall and rolls
    off it (spin 9.7 rad/s about the wall's normal x its velocity), the normal speed e times the
    incoming. On a static wall (an exact signed distance) and on the face of a ball of 1 m radius
    and 10 t (a body pair of two exact spheres): the contact law is right for both kinds of
    contact set (MuJoCo on the wall: -0.496 m/s along it, rigid -0.486). A box body's exact faces:
    ``test_a_ball_meeting_a_box_face_off_centre_leaves_it_straight``. The native cases are skipped where the native extension does not build
    (no compiler)."""
    _needs(engine)
    r, mu, e = 0.05, 0.5, 0.3
    vn, vt = 1.71, -0.68
    ball = ball_body("ball", radius=r, mass=0.4, friction=mu, restitution=e)
    if surface == "wall":
        wall = StaticShape.make("wall", "box", position=(-0.5, 0.0, 0.0), half=(0.5, 1.0, 1.0),
                                friction=mu, restitution=e)
        world = _weightless([ball], [wall], mu, e)
        state = world.state([[0.1, 0.0, 0.0]], linear_velocity=[[-vn, vt, 0.0]])
    else:
        world = _weightless([ball, _heavy_ball(mu, e)], [], mu, e)
        # the ball meets the big one 29 ms on, the impact lasts about 25 ms: started 2.8 cm to the
        # side it is on the line of centres mid-impact, so the curved face's normal turns as much
        # one way as the other (started on that line it pushes the ball on by 0.04 m/s)
        state = world.state([[0.1, 0.028, 0.0], [-1.0, 0.0, 0.0]],
                            linear_velocity=[[-vn, vt, 0.0], [0.0, 0.0, 0.0]])
    traj = rollout(world, state, steps=100, engine=engine)  # the impact is over at about 0.06 s
    v = traj.final.linear_velocity[0, 0].numpy()
    w = traj.final.angular_velocity[0, 0].numpy()
    assert abs(v[1] - 5.0 / 7.0 * vt) < 0.02, v  # measured -0.486 and -0.478 (rigid -0.486)
    assert abs(w[2] - 5.0 / 7.0 * vt / r) < 0.5, w  # rolls off: spin = v_t / r about -z
    # the rebound: measured 0.543 on the wall, 0.580 on the big ball (the normal there is the line
    # of centres, 1.6 deg off x mid-impact); head-on 0.553 on either, e 0.32 at this speed
    assert abs(v[0] - e * vn) < 0.15 * e * vn, v
    assert abs(v[2]) < 1e-9 and abs(w[0]) < 1e-9 and abs(w[1]) < 1e-9


@pytest.mark.parametrize("engine", ["native", "torch"])
def test_a_ball_meeting_a_box_face_off_centre_leaves_it_straight(engine):
    """A ball (5 cm) flies at 1.71 m/s straight onto a face of a resting box (10 t, so it stays),
    without gravity, 0 to 30 mm off the face's centre: a flat face sends it straight back. The box
    body meets other bodies with its exact faces (``BodySpec.box_half``); as a union of spheres
    (its packing, ``geometry/box_spheres.py``) the face kicked the ball sideways at up to 0.15 m/s
    (docs/physics-fidelity.md, "ball meets a box face 1 cm off centre")."""
    from dejaview.geometry.box_spheres import box_spheres

    _needs(engine)
    r, e = 0.05, 0.3
    box = _heavy_box(*box_spheres((0.2, 0.15, 0.1)), e)
    offsets = [0.0, 0.005, 0.01, 0.015, 0.02, 0.03]
    world = _weightless([ball_body("ball", radius=r, mass=0.4, restitution=e), box], [], e=e)
    state = world.state([[[0.25, y, 0.0], [0.0, 0.0, 0.0]] for y in offsets],
                        linear_velocity=[[[-1.71, 0.0, 0.0], [0.0, 0.0, 0.0]]] * len(offsets))
    traj = rollout(world, state, steps=100, engine=engine)
    v = traj.final.linear_velocity[:, 0].numpy()
    assert np.all(v[:, 0] > 0.4), v  # it rebounded (e 0.3 of 1.71 m/s)
    assert np.abs(v[:, 1:]).max() < 1e-4, v  # the 10 t box turns a little: 2e-5 m/s at 30 mm


@pytest.mark.parametrize("engine", ["native", "torch"])
def test_a_small_fast_ball_does_not_pass_through_a_box_body(engine):
    """A ball of 5 mm at 6 m/s onto a resting box's face (10 t), without gravity: the contact sinks
    it by about v / omega_0 = 24 mm, far past its radius, so its centre crosses the face; the box's
    surface then partners it from behind the nearest face (``contacts.box_partner``) and it comes
    back out the way it went in, wherever on the face it lands farther from the face's border than
    it sinks (nearer, the nearest face is another one, as for a static box's distance)."""
    _needs(engine)
    r, m = 0.005, 0.01
    box = _heavy_box(np.zeros((1, 3)), np.array([0.04]), 0.3)
    world = _weightless([ball_body("ball", radius=r, mass=m, restitution=0.3), box], [])
    starts = [[[0.2, y, z], [0.0, 0.0, 0.0]] for y, z in ((0.0, 0.0), (0.03, -0.02), (-0.04, 0.015))]
    state = world.state(starts, linear_velocity=[[[-6.0, 0.0, 0.0], [0.0, 0.0, 0.0]]] * len(starts))
    traj = rollout(world, state, steps=60, engine=engine)
    x = traj.states.position[:, :, 0, 0].numpy()  # (T, B)
    assert x.min() < 0.1 - 0.005  # its centre went in, past the face
    assert np.all(traj.final.position[:, 0, 0].numpy() > 0.1 + r)  # and came back out
    assert np.all(traj.final.linear_velocity[:, 0, 0].numpy() > 1.0)


def test_frictionless_elastic_collision_conserves_momentum():
    a = ball_body("a", mass=1.0, friction=0.0, restitution=1.0)
    b = ball_body("b", mass=1.0, friction=0.0, restitution=1.0)
    world = make_world([a, b], [], gravity=(0.0, 0.0, 0.0), dt=0.002, substeps=2,
                       friction=0.0, restitution=1.0)
    state = world.state([[0.0, 0.0, 0.0], [0.3, 0.01, 0.0]],
                        linear_velocity=[[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    traj = rollout(world, state, steps=300)
    m = world.mass[:, None]
    p0 = (m * state.linear_velocity[0]).sum(0)
    p1 = (m * traj.final.linear_velocity[0]).sum(0)
    assert (p1 - p0).norm() / p0.norm() < 0.01
    e0 = 0.5 * (m * state.linear_velocity[0] ** 2).sum()
    e1 = 0.5 * (m * traj.final.linear_velocity[0] ** 2).sum()
    assert abs(e1 - e0) / e0 < 0.05  # (nearly) elastic
    # an off-centre hit sends b off along the line of centres
    assert traj.final.linear_velocity[0, 1, 0] > 0.9


def test_float32_runs_and_matches_float64():
    world = make_world([ball_body()], [StaticShape.make("floor", "plane")])
    s64 = world.state([[0.0, 0.0, 0.3]], linear_velocity=[[1.0, 0.0, 0.0]])
    t64 = rollout(world, s64, steps=200)
    w32 = world.to(dtype=torch.float32)
    t32 = rollout(w32, s64.to(dtype=torch.float32), steps=200)
    assert t32.final.position.dtype == torch.float32
    assert torch.allclose(t32.final.position.double(), t64.final.position, atol=2e-3)
