"""The shared physics' marginal on a grid (``dejaview.inference.physics_marginal``): each scene's
start integrated out by Laplace at each node."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from dejaview.inference.identify import identify, levenberg_marquardt
from dejaview.inference.physics_marginal import physics_grid, scan
from dejaview.inference.params import IdentifyParams, SearchParams
from dejaview.scene import Scene
from tests.inference.tracking import position_targets

SCENE = """<scene version="1" name="{name}">
  <simulation dt="0.002" duration="0.3" friction="{friction}" restitution="0.2"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="box" shape="box" size="0.1 0.1 0.1" mass="0.5">
    <pose position="{x} 0 0.05"/><velocity linear="{vx} 0 0" angular="0 0 0"/>
  </object>
  <inference source="box" loss="position">
    {targets}
    <optimize position="true" orientation="false" linear-velocity="true" angular-velocity="false"/>
    <start-area min="-0.2 -0.1 0.05" max="0.2 0.1 0.05"/>
    <observation sigma="0.001"/>
    <prior speed="2.0"/>
    <physics-prior friction="0.5"/>
  </inference>
</scene>"""
TIMES = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3)
SLIDES = ({"x": -0.1, "vx": 1.6}, {"x": 0.05, "vx": 1.2})


def _slide(k: int) -> Scene:
    """Slide k of a box on the floor at friction 0.3, tracked at TIMES; the scene says 0.4."""
    true = Scene.from_string(SCENE.format(name=f"slide-{k}", friction=0.3, targets='<target position="0 0 0"/>',
                                          **SLIDES[k]))
    return Scene.from_string(SCENE.format(name=f"slide-{k}", friction=0.4, targets=position_targets(true, TIMES),
                                          x=0.0, vx=0.0))


FAST = IdentifyParams(search=replace(SearchParams(), budget=800), lm_iterations=25, rounds=0, grid=11, scan=0)


@pytest.fixture(scope="module")
def identified():
    return identify([_slide(0), _slide(1)], FAST)


def test_grid_agrees_with_laplace_where_the_posterior_is_gaussian(identified):
    """A box sliding (not yet stopped) is a smooth function of the friction: the grid's interval
    is as wide as the joint Laplace approximation's, near it, and both hold the truth."""
    laplace = replace(identified, grid=None)
    g = identified.physics()["intervals"]["friction"]
    l_ = laplace.physics()["intervals"]["friction"]
    assert "grid" in identified.physics()["intervals_from"]
    assert "Laplace" in laplace.physics()["intervals_from"]
    for entry in (g, l_):
        assert entry["90%"][0] <= 0.3 <= entry["90%"][1]
    wg, wl = g["90%"][1] - g["90%"][0], l_["90%"][1] - l_["90%"][0]
    assert 0.7 < wg / wl < 1.4, (g, l_)
    assert abs(g["median"] - l_["median"]) < 0.5 * wl, (g, l_)
    assert identified.to_json()["grid"]["nodes"] == 11


def test_grid_widens_until_its_edges_hold_no_mass(identified):
    """Started far too narrow (0.3 Laplace standard deviations), the grid widens its axis until
    its edges hold (almost) nothing, and its mass sits where the first grid's did."""
    params = replace(FAST, grid=7, grid_sds=0.3, grid_min_width=0.01, grid_widen=4.0, grid_passes=3)
    grid = physics_grid(identified.joint, identified.x, identified.covariance, params)
    assert grid.passes >= 2
    assert float(grid.widths[0]) > 0.3 * float(identified.covariance[-1, -1].sqrt()) * 2
    edge = (grid.z[:, 0] - identified.x[-1]).abs() >= grid.widths[0] * 0.999
    assert float(grid.weights[edge].sum()) < 0.05
    mean = float((grid.weights * grid.z[:, 0]).sum())
    first = float((identified.grid.weights * identified.grid.z[:, 0]).sum())
    assert abs(mean - first) < 0.5 * float(identified.covariance[-1, -1].sqrt())


def test_the_scan_over_the_prior_leads_back_to_a_unimodal_maximum(identified):
    """The physics scanned over its prior: the nodes of least joint cost come first, and refined
    jointly the best of them reaches the maximum identify found (the slides have one)."""
    params = replace(FAST, scan=9, scan_keep=2, grid_iterations=6)
    trial = scan(identified.joint, identified.x, params)
    assert trial.shape == (2, identified.x.numel())
    assert float(trial[:, -1].abs().max()) <= params.scan_width + 1e-9
    with torch.no_grad():
        costs = identified.joint.cost(trial)
    assert bool(torch.isfinite(costs).all())
    _, refined = levenberg_marquardt(identified.joint, trial[:1], 25)
    assert float(refined[0]) <= identified.cost + 0.05
