"""The floor's symmetry (``dejaview.inference.symmetry``): the rollout of a moved start is the moved
rollout, the move along it leaves its target invariant, and only scenes that have it use it."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from dejaview.inference.posterior import Posterior, PosteriorSettings
from dejaview.backends.spheres import SpheresProblem
from dejaview.inference.reference import log_density, log_prior_density, prior_draws
from dejaview.inference.symmetry import FloorSymmetry, compared_records, orbit_walk
from dejaview.scene import (InferenceSettings, Observation, Optimize, Pose, Prior, Scene, SceneObject,
                            SimulationSettings, StartArea, Target)


def thrown_box(duration=0.6, statics=None, loss="pose", optimize=None, speed=1.0):
    """A box tossed onto a floor (the calibration bench's ``box_thrown``, shorter)."""
    floor = SceneObject(id="floor", shape="plane", fixed=True)
    return Scene(
        name="box-thrown", gravity=(0.0, 0.0, -9.81),
        simulation=SimulationSettings(dt=0.002, duration=duration, friction=0.5, restitution=0.2),
        objects=(floor, *(statics or ()),
                 SceneObject(id="box", shape="box", size=(0.12, 0.08, 0.06), mass=0.3, pose=Pose((0.0, 0.0, 0.3)))),
        inference=InferenceSettings(
            source="box", targets=(Target(position=(0.1, -0.05, 0.03), orientation=(0.96, 0.0, 0.0, 0.28)),),
            loss=loss, evaluate="final",
            optimize=optimize or Optimize(position=True, orientation=True, linear_velocity=True,
                                          angular_velocity=True),
            start_area=StartArea(min=(-0.3, -0.3, 0.3), max=(0.3, 0.3, 0.3)),
            prior=Prior(speed=speed, spin=3.0, tilt=0.3), observation=Observation(sigma=0.01, angle_sigma=0.1)))


def posterior_of(scene):
    return Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))


def test_the_rollout_of_a_moved_start_is_the_moved_rollout():
    post = posterior_of(thrown_box())
    sym = FloorSymmetry.of(post)
    assert sym == FloorSymmetry(axes=(0, 1), rotate=True)
    gen = torch.Generator().manual_seed(3)
    x = post.sample(6, gen)
    x[:, :2] = 0.5 * x[:, :2].clamp(-1, 1)  # inside the start area after the move
    theta = 2.0 * torch.randn(6, generator=gen, dtype=torch.float64)
    t = 0.05 * torch.randn(6, 2, generator=gen, dtype=torch.float64)
    y, log_jac = sym.act(post.layout, x, theta, t)
    assert torch.isfinite(log_jac).all()
    pivot = post.layout.decode(x)["position"]
    moved = sym.act_trajectory(post.problem.simulate(x), pivot, theta, t)
    fresh = post.problem.simulate(y)
    assert torch.allclose(moved.states.position, fresh.states.position, atol=1e-9)
    assert torch.allclose(moved.states.linear_velocity, fresh.states.linear_velocity, atol=1e-7)
    dot = (moved.states.orientation * fresh.states.orientation).sum(-1).abs()
    assert float(dot.min()) > 1 - 1e-12
    # the densities from the moved rollout are those of a fresh one
    assert torch.allclose(log_density(post, y, trajs=[moved]), log_density(post, y), rtol=1e-9)
    # the start moved: position by t, the end by theta about the start and t
    start_y = post.layout.decode(y)["position"]
    assert torch.allclose(start_y[:, :2], pivot[:, :2] + t, atol=1e-12)


def test_every_physics_variant_of_model_uncertainty_moves_alike():
    """With ``<model-uncertainty>`` the likelihood averages K variants' rollouts: the moved
    rollouts give the density of fresh ones."""
    from dejaview.inference.model_uncertainty import ModelVariants

    scene = thrown_box()
    problem = SpheresProblem.from_scene(scene)
    model = ModelVariants.from_world(problem.world, friction=0.2, restitution=0.2)
    post = Posterior(problem, PosteriorSettings.from_scene(scene), model=model)
    sym = FloorSymmetry.of(post)
    gen = torch.Generator().manual_seed(4)
    x = post.sample(4, gen)
    x[:, :2] = 0.5 * x[:, :2].clamp(-1, 1)
    theta = torch.tensor([0.5, -1.0, 2.0, 0.1], dtype=torch.float64)
    t = 0.02 * torch.randn(4, 2, generator=gen, dtype=torch.float64)
    y, _ = sym.act(post.layout, x, theta, t)
    pivot = post.layout.decode(x)["position"]
    trajs = post.trajectories(x)
    assert len(trajs) == model.count > 1
    moved = [sym.act_trajectory(tr, pivot, theta, t) for tr in trajs]
    assert torch.allclose(log_density(post, y, trajs=moved), log_density(post, y), rtol=1e-9)


def test_the_move_inverts_and_its_jacobian_is_the_determinant():
    post = posterior_of(thrown_box())
    sym = FloorSymmetry.of(post)
    lay = post.layout
    gen = torch.Generator().manual_seed(5)
    x = post.sample(4, gen)
    x[:, :2] = 0.5 * x[:, :2].clamp(-1, 1)
    theta = torch.tensor([0.3, -2.0, 3.0, 1.0], dtype=torch.float64)
    t = torch.tensor([[0.01, -0.02], [0.0, 0.05], [-0.03, 0.0], [0.02, 0.02]], dtype=torch.float64)
    y, log_jac = sym.act(lay, x, theta, t)
    back, log_back = sym.act(lay, y, -theta, -t)
    assert torch.allclose(back, x, atol=1e-10)
    assert torch.allclose(log_jac, -log_back, atol=1e-10)
    for i in range(4):  # the log determinant of the Jacobian, by finite differences
        def f(v, i=i):
            return sym.act(lay, v[None], theta[i:i + 1], t[i:i + 1])[0][0]
        jac = torch.autograd.functional.jacobian(f, x[i])
        assert math.isclose(float(torch.linalg.slogdet(jac)[1]), float(log_jac[i]), abs_tol=1e-8)
    # leaving the start area: infinite cost
    _, out = sym.act(lay, x[:1], torch.zeros(1, dtype=torch.float64), torch.tensor([[1.0, 0.0]], dtype=torch.float64))
    assert out[0] == -math.inf


def test_orbit_coordinates_invert_and_their_volume_is_the_determinant():
    post = posterior_of(thrown_box())
    sym = FloorSymmetry.of(post)
    lay = post.layout
    x = post.sample(5, torch.Generator().manual_seed(8))
    r, g, log_vol = sym.coordinates(lay, x)
    assert r.shape == (5, 8) and g.shape == (5, 3)
    back, ok = sym.parameters(lay, r, g)
    assert ok.all() and torch.allclose(back, x, atol=1e-10)
    for i in range(5):  # log |det dx/d(r, g)| by automatic differentiation, up to one constant
        def f(v, i=i):
            return sym.parameters(lay, v[None, :8], v[None, 8:])[0][0]
        jac = torch.autograd.functional.jacobian(f, torch.cat([r[i], g[i]]))
        diff = float(torch.linalg.slogdet(jac)[1] - log_vol[i])
        if i == 0:
            constant = diff
        assert math.isclose(diff, constant, abs_tol=1e-8)
    # a motion adds to g and leaves r
    y, _ = sym.act(lay, x, torch.full((5,), 0.4, dtype=torch.float64), torch.zeros(5, 2, dtype=torch.float64))
    r2, g2, _ = sym.coordinates(lay, y)
    assert torch.allclose(r2, r, atol=1e-10)
    assert torch.allclose(torch.remainder(g2[:, 0] - g[:, 0], 2 * math.pi), torch.full((5,), 0.4, dtype=torch.float64))


def _ks_same(a, b):
    """Two-sample Kolmogorov-Smirnov statistic below its 0.1 % critical value."""
    n, m = a.shape[0], b.shape[0]
    grid = torch.sort(torch.cat([a, b])).values
    cdf_a = torch.searchsorted(torch.sort(a).values, grid, right=True) / n
    cdf_b = torch.searchsorted(torch.sort(b).values, grid, right=True) / m
    return float((cdf_a - cdf_b).abs().max()) < 1.95 * math.sqrt((n + m) / (n * m))


@pytest.mark.parametrize("step, beta, speed", [(None, 1e-3, 1.0), (None, 0.05, 1.0), (0.5, 0.05, 1.0),
                                               (None, 0.05, 5.0)])
def test_the_orbit_walk_keeps_the_prior_when_it_is_the_target(step, beta, speed):
    """With the prior as its target, 2000 prior draws moved five times stay prior draws: the
    Jacobians, the importance weights and the pseudo-marginal acceptance are right (checked:
    without the coordinates' volume the first case fails, without the proposal's density in
    the weights the second; at 5 m/s the ends lie half a metre from the starts, so the
    proposal's turn about the end point matters)."""
    post = posterior_of(thrown_box(duration=0.1, speed=speed))
    sym = FloorSymmetry.of(post)
    lay = post.layout
    gen = torch.Generator().manual_seed(11)
    n = 2000
    x = prior_draws(post, n, gen)
    before = x.clone()
    moved = torch.zeros(n, dtype=torch.bool)
    for _ in range(5):
        d = sym.coordinates(lay, x)[0].shape[1]
        dx = None if step is None else step * torch.randn(n, d, generator=gen, dtype=torch.float64)
        x, _, ok, _ = orbit_walk(post, sym, x, lambda y, lp: log_prior_density(post, y), beta, gen, step=dx)
        moved |= ok
    assert float(moved.double().mean()) > 0.1
    fresh = prior_draws(post, n, torch.Generator().manual_seed(12))
    for j, name in enumerate(lay.names()):
        f = torch.sigmoid if name.startswith("position") else (lambda v: v)
        assert _ks_same(f(x[:, j]), f(fresh[:, j])), name
    assert not torch.equal(before, x)


def test_the_orbit_walk_carries_ends_onto_the_observation():
    post = posterior_of(thrown_box())
    sym = FloorSymmetry.of(post)
    gen = torch.Generator().manual_seed(2)
    x = prior_draws(post, 64, gen)
    lp0 = log_density(post, x)
    y, lp, ok, ends = orbit_walk(post, sym, x, lambda y, lp: lp, 1.0, gen)
    # those whose aligned start lies in the start area move, and their ends now fit in position
    # and heading (the others' would start outside the area)
    assert float(ok.double().mean()) > 0.2
    assert float((lp - lp0)[ok].median()) > 10
    assert torch.allclose(lp, log_density(post, y), rtol=1e-8)
    # the ends it returns are those of y's rollouts; given as known, x's rollouts are not run again
    fresh = compared_records(post, post.problem.simulate(y))
    assert torch.allclose(ends[0].states.position, fresh.states.position, atol=1e-9)
    before = post.rollouts
    step = 0.05 * torch.randn(64, 8, generator=gen, dtype=torch.float64)
    z, lp_z, across, ends_z = orbit_walk(post, sym, y, lambda y, lp: lp, 1.0, gen, step=step,
                                         known=(ends, torch.ones(64, dtype=torch.bool)))
    assert post.rollouts == before + 64  # the proposed orbits' only
    assert across.any() and not across.all()
    fresh = compared_records(post, post.problem.simulate(z))
    assert torch.allclose(ends_z[0].states.position, fresh.states.position, atol=1e-9)
    assert torch.allclose(lp_z, log_density(post, z), rtol=1e-8)


def test_the_orbit_proposal_turns_about_the_end_point():
    """A box that ends a metre from its start: the proposal's motions keep its end near the
    observed one whatever their turn (a turn of 0.1 rad about the start would move it 10 cm)."""
    post = posterior_of(thrown_box())
    sym = FloorSymmetry.of(post)
    lay = post.layout
    x = torch.zeros(1, lay.size, dtype=torch.float64)
    x[0, lay.block_slice("linear_velocity")] = torch.tensor([2.5, 1.0, 0.0]) / lay.scale["linear_velocity"]
    traj = post.problem.simulate(x)
    pivot = lay.decode(x)["position"]
    end = traj.states.position[-1, 0, post.problem.source]
    assert float((end - pivot[0])[:2].norm()) > 0.8
    theta_c, t_c, arm = sym.aligning(post, traj, pivot)
    spread = sym.spreads(post, 1.0)
    theta, t = sym.draw((theta_c, t_c), arm, spread, 2000, torch.Generator().manual_seed(5))
    assert float(theta.std()) > 0.1  # the turns spread as the heading's noise says
    moved = sym.act_trajectory(compared_records(post, traj).select(torch.zeros(2000, dtype=torch.long)),
                               pivot.expand(2000, 3), theta[0], t[0])
    off = moved.states.position[-1, :, post.problem.source, :2] - post._target_com[:2]
    assert float(off.norm(dim=-1).max()) < 6 * spread[1]
    # its density is that of the normal it draws from: the end's offset and the turn
    z = off / spread[1]
    d = (theta[0] - theta_c) / spread[0]
    expected = (-0.5 * (z * z).sum(-1) - 0.5 * d * d
                - math.log(spread[0] * math.sqrt(2 * math.pi)) - 2 * math.log(spread[1] * math.sqrt(2 * math.pi)))
    got = sym.log_proposal(theta[0], t[0], (theta_c.expand(2000), t_c.expand(2000, 2)), arm.expand(2000, 3), spread)
    assert torch.allclose(got, expected, atol=1e-9)


@pytest.mark.parametrize("case", ["table", "fixed_tilt_with_velocity", "tilted_floor", "best_record"])
def test_scenes_without_the_symmetry_do_not_use_it(case):
    if case == "table":
        scene = thrown_box(statics=(SceneObject(id="table", shape="box", size=(0.5, 0.5, 0.1), fixed=True,
                                                pose=Pose((1.0, 0.0, 0.05))),))
        assert FloorSymmetry.of(posterior_of(scene)) is None
    elif case == "fixed_tilt_with_velocity":  # no turn (orientation fixed), translations still
        scene = thrown_box(optimize=Optimize(position=True, orientation=False, linear_velocity=True,
                                             angular_velocity=True))
        assert FloorSymmetry.of(posterior_of(scene)) == FloorSymmetry(axes=(0, 1), rotate=False)
    elif case == "best_record":  # the likelihood reads every record: not moved along the orbits
        scene = thrown_box()
        moving = replace(scene.inference.target, moving=True)  # seen in motion at a moment not known
        scene = replace(scene, inference=replace(scene.inference, evaluate="best", targets=(moving,)))
        assert FloorSymmetry.of(posterior_of(scene)) is None
    else:
        scene = thrown_box()
        tilted = replace(scene.objects[0], pose=Pose((0.0, 0.0, 0.0), (0.995, 0.0998, 0.0, 0.0)))
        scene = replace(scene, objects=(tilted, *scene.objects[1:]))
        assert FloorSymmetry.of(posterior_of(scene)) is None
