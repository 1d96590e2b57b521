"""The posterior sampler (``dejaview.inference.sampling``): exact on posteriors known in closed form,
every mode weighted by its mass, and wired through solve, the CLI and result files."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.inference.params import ReportParams
from dejaview.inference.posterior import PosteriorSettings
from dejaview.inference.posterior_report import (
    CSV_HEADER,
    PATHS_HEADER,
    agreement_warning,
    path_samples,
    read_csv,
    rhat,
    summary,
    weighted_quantiles,
)
from dejaview.inference.reference import Mixture, log_base_density
from dejaview.inference.params import SamplerParams
from dejaview.inference.sampling import Sampler
from dejaview.inference.sampling import PosteriorSamples as Samples
from dejaview.inference.search import Mode
from dejaview.scene import Optimize, PosteriorRequest, Scene

SCENES = Path(__file__).resolve().parents[2] / "examples" / "scenes"


@dataclass
class FakeLayout:
    """P free parameters, all in the ``linear_velocity`` block (no base-measure terms)."""

    size: int
    lo: object = None
    free: dict = field(default_factory=lambda: {"position": False, "orientation": False,
                                                "linear_velocity": True, "angular_velocity": False})
    scale: dict = field(default_factory=lambda: {"position": 0.1, "orientation": 0.5,
                                                 "linear_velocity": 1.0, "angular_velocity": 5.0})

    def block_slice(self, block):
        return slice(0, self.size) if block == "linear_velocity" else slice(0, 0)


class FakePosterior:
    """A posterior given by ``neg_log(x) (B,)`` and a residual function for the Laplace step."""

    def __init__(self, size, neg_log, residuals, feasible=None):
        self.layout = FakeLayout(size)
        self.settings = PosteriorSettings(speed=1.0)
        self.neg_log, self.res = neg_log, residuals
        self.feasible_fn = feasible
        self.rollouts = 0
        self.checked = 0

    def feasible(self, x):
        self.checked += x.shape[0]
        return torch.ones(x.shape[0], dtype=torch.bool) if self.feasible_fn is None else self.feasible_fn(x)

    def cost(self, x, feasibility=True, trajs=None):
        self.rollouts += x.shape[0]
        c = self.neg_log(x)
        if feasibility:
            c = torch.where(self.feasible(x), c, torch.full_like(c, math.inf))
        return c, c, c

    def jacobian(self, x):
        x = x.detach().clone().requires_grad_(True)
        r = self.res(x)
        rows = [torch.autograd.grad(r[:, i].sum(), x, retain_graph=True)[0] for i in range(r.shape[1])]
        return r.detach(), torch.stack(rows, 1)


def test_a_linear_gaussian_posterior_is_sampled_exactly():
    """R(x) = A x - b: the posterior is N(A^+ b, (A^T A)^-1); mean and covariance within Monte Carlo
    error of 2000 samples, and the 90 % intervals where the normal's are."""
    torch.manual_seed(0)
    A = torch.tensor([[2.0, 0.5, 0.0], [0.0, 1.0, 0.3], [0.4, 0.0, 3.0], [0.1, 0.2, 0.1]], dtype=torch.float64)
    b = torch.tensor([1.0, -0.5, 0.7, 0.2], dtype=torch.float64)

    def res(x):
        return x @ A.T - b

    post = FakePosterior(3, lambda x: 0.5 * (res(x) ** 2).sum(-1), res)
    cov = torch.linalg.inv(A.T @ A)
    mean = cov @ A.T @ b
    off = Mode(mean + torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64), 0.0, 0.0, 0.0)  # a rough mode
    smp = Sampler(SamplerParams(seed=1)).sample(post, [off], 2000)
    assert torch.allclose(smp.weights.sum(), torch.tensor(1.0, dtype=torch.float64))
    x = smp.x
    sd = torch.sqrt(torch.diagonal(cov))
    assert torch.all((x.mean(0) - mean).abs() < 4 * sd / math.sqrt(2000 / 10)), (x.mean(0), mean)
    emp = torch.cov(x.T)
    assert torch.allclose(torch.sqrt(torch.diagonal(emp)), sd, rtol=0.12), (torch.diagonal(emp), sd ** 2)
    q = weighted_quantiles(x, smp.weights, [0.05, 0.95])
    assert torch.allclose(q[1] - q[0], 2 * 1.6449 * sd, rtol=0.15)


def test_infeasible_starts_get_no_sample_and_only_kept_proposals_are_checked():
    """A standard normal cut at x0 < 0.5 (starts beyond it interpenetrate): no sample beyond the
    cut, the truncated normal's mean, and the costly check ran on far fewer candidates than were
    simulated (only on proposals the likelihood would accept)."""
    post = FakePosterior(2, lambda x: 0.5 * (x * x).sum(-1), lambda x: x, feasible=lambda x: x[:, 0] < 0.5)
    zero = Mode(torch.zeros(2, dtype=torch.float64), 0.0, 0.0, 0.0)
    smp = Sampler(SamplerParams(seed=4)).sample(post, [zero], 2000)
    assert float(smp.x[:, 0].max()) < 0.5
    # mean of N(0, 1) below 0.5: -pdf(0.5) / cdf(0.5)
    expected = -math.exp(-0.125) / math.sqrt(2 * math.pi) / (0.5 * (1 + math.erf(0.5 / math.sqrt(2))))
    mean = float((smp.weights * smp.x[:, 0]).sum())
    assert abs(mean - expected) < 0.08, (mean, expected)
    assert post.checked < 0.7 * post.rollouts, (post.checked, post.rollouts)


def test_a_long_thin_ridge_is_sampled_along_its_whole_length():
    """x0 + x1 = 1 observed to 0.01, each parameter's prior N(0, 1) (the ``linear_velocity`` block):
    the posterior is a ridge 70x longer than wide, the prior alone setting its extent (the ball's
    start x against its x velocity); the marginal spread along the ridge is the normal's."""
    a = torch.tensor([[100.0, 100.0]], dtype=torch.float64)  # (x0 + x1 - 1) / 0.01

    def res(x):
        return torch.cat([x @ a.T - 100.0, x], -1)  # observation, then the prior's residuals

    post = FakePosterior(2, lambda x: 0.5 * (res(x) ** 2).sum(-1), res)
    prec = a.T @ a + torch.eye(2, dtype=torch.float64)
    cov = torch.linalg.inv(prec)
    mean = cov @ (a.T @ torch.tensor([100.0], dtype=torch.float64))
    start = Mode(mean + torch.tensor([0.2, -0.2], dtype=torch.float64), 0.0, 0.0, 0.0)
    smp = Sampler(SamplerParams(seed=3)).sample(post, [start], 1000)
    along = (smp.x - mean) @ torch.tensor([1.0, -1.0], dtype=torch.float64) / math.sqrt(2)
    true_sd = math.sqrt(float(torch.tensor([1.0, -1.0], dtype=torch.float64) @ cov
                              @ torch.tensor([1.0, -1.0], dtype=torch.float64)) / 2)
    assert float(along.std()) == pytest.approx(true_sd, rel=0.15)
    assert abs(float(along.mean())) < 0.25 * true_sd


def test_every_mode_is_covered_in_proportion_to_its_mass():
    """Two separated normal modes holding 0.7 and 0.3 of the mass (different widths, so their
    densities at the peaks differ from their masses): the samples split 0.7 / 0.3."""
    m = torch.tensor([-1.0, 1.5], dtype=torch.float64)
    s = torch.tensor([0.05, 0.2], dtype=torch.float64)
    w = torch.tensor([0.7, 0.3], dtype=torch.float64)

    def neg_log(x):
        z = (x[:, :1] - m) / s
        return -torch.logsumexp(torch.log(w / s) - 0.5 * z * z, -1)

    def res(x):
        k = ((x[:, :1] - m).abs() / s).argmin(-1)
        return (x[:, :1] - m[k, None]) / s[k, None]

    post = FakePosterior(1, neg_log, res)
    modes = [Mode(m[i:i + 1].clone(), float(neg_log(m[i:i + 1, None])), 0.0, 0.0) for i in range(2)]
    smp = Sampler(SamplerParams(seed=2)).sample(post, modes, 3000)
    share = float(smp.weights[smp.x[:, 0] < 0.25].sum())
    assert share == pytest.approx(0.7, abs=0.04)
    assert float(smp.x[smp.x[:, 0] > 0.25, 0].std()) == pytest.approx(0.2, rel=0.15)


def test_mixture_density_integrates_to_one():
    chol = torch.linalg.cholesky(torch.tensor([[[0.5, 0.1], [0.1, 0.3]], [[0.2, 0.0], [0.0, 0.8]]],
                                              dtype=torch.float64))
    q = Mixture(torch.tensor([[0.0, 0.0], [2.0, -1.0]], dtype=torch.float64), chol,
                torch.log(torch.tensor([0.4, 0.6], dtype=torch.float64)))
    g = torch.linspace(-12, 14, 561, dtype=torch.float64)
    xx, yy = torch.meshgrid(g, g, indexing="ij")
    pts = torch.stack([xx.reshape(-1), yy.reshape(-1)], -1)
    total = float(q.log_prob(pts).exp().sum()) * float(g[1] - g[0]) ** 2
    assert total == pytest.approx(1.0, abs=0.02)  # Student-t tails beyond the grid hold the rest
    x, k = q.sample(20000, torch.Generator().manual_seed(0))
    assert float((k == 1).double().mean()) == pytest.approx(0.6, abs=0.02)


def test_flat_orientation_has_the_haar_density_up_to_pi():
    from dejaview.backends.params import layout_from_scene
    from dejaview.inference.posterior import Posterior

    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    scene = replace(scene, inference=replace(scene.inference, optimize=Optimize(
        position=False, orientation=True, linear_velocity=False, angular_velocity=False)))

    class P:  # what log_base_density reads
        layout = layout_from_scene(scene)
        settings = PosteriorSettings()

    s = P.layout.scale["orientation"]
    angles = torch.tensor([0.0, 1.0, 3.0, 3.2], dtype=torch.float64)
    x = torch.zeros(4, 3, dtype=torch.float64)
    x[:, 2] = angles / s
    d = log_base_density(P, x)
    assert float(d[0]) == pytest.approx(math.log(0.5))
    assert float(d[1]) == pytest.approx(math.log(1 - math.cos(1.0)))
    assert float(d[2]) == pytest.approx(math.log((1 - math.cos(3.0)) / 9))
    assert d[3] == -math.inf
    assert isinstance(Posterior, type)


def ramp_scene(samples: int | None = None) -> Scene:
    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    post = None if samples is None else PosteriorRequest(samples=samples)
    return replace(scene, inference=replace(scene.inference, posterior=post))


def test_solve_with_samples_writes_posterior_csv_and_summary(tmp_path):
    result = solve(ramp_scene(samples=200))
    assert result.posterior is not None and result.posterior.x.shape == (200, 2)
    paths = result.write(tmp_path)
    weights, states = read_csv(paths["posterior"])
    assert (tmp_path / "posterior.csv").read_text().splitlines()[0] == ",".join(CSV_HEADER)
    assert len(weights) == 200 and weights.min() >= 0 and weights.sum() == pytest.approx(1.0)
    assert np.allclose(states[:, 2], 0.55) and np.allclose(np.linalg.norm(states[:, 3:7], axis=1), 1.0)
    data = json.loads(paths["result"].read_text())
    post = data["posterior"]
    assert post["samples"] == 200 and sum(m["probability"] for m in post["modes"]) == pytest.approx(1.0, abs=1e-3)
    # two independent runs of 100 that agree: the end pins the ramp's start
    assert post["sampler"]["runs"] == 2 and torch.bincount(result.posterior.run).tolist() == [100, 100]
    assert post["agreement"]["runs_agree"] and post["agreement"]["max_rhat"] <= ReportParams.rhat_limit
    assert len(post["sampler"]["log_evidence"]) == 2 and all(map(math.isfinite, post["sampler"]["log_evidence"]))
    assert all(iv["rhat"] <= ReportParams.rhat_limit for iv in post["intervals"].values())
    # the same samples with one run moved off: flagged
    moved = result.posterior.x.clone()
    second = result.posterior.run == 1
    moved[second, 0] += 2 * moved[:, 0].std()
    flagged = summary(replace(result.posterior, x=moved), result.problem.layout, result.optimization.modes)
    assert not flagged["agreement"]["runs_agree"] and flagged["intervals"]["position.x"]["rhat"] > ReportParams.rhat_limit
    assert flagged["intervals"]["position.y"]["rhat"] <= ReportParams.rhat_limit
    assert agreement_warning(post["agreement"], "these intervals") is None
    line = agreement_warning(flagged["agreement"], "these intervals")
    assert "disagree" in line and f"{flagged['agreement']['max_rhat']:.2f}" in line and "\n" not in line
    start = data["initial_state"]["position"]
    for axis, name in ((0, "position.x"), (1, "position.y")):
        iv = post["intervals"][name]
        assert iv["90%"][0] <= iv["50%"][0] <= iv["median"] <= iv["50%"][1] <= iv["90%"][1]
        assert iv["90%"][0] - 0.02 <= start[axis] <= iv["90%"][1] + 0.02  # the MAP sits in the bulk
    # a few samples' pasts: each starts at its posterior.csv row and ends where its own rollout ends
    rows = list(csv.reader(paths["posterior_paths"].open()))
    assert tuple(rows[0]) == PATHS_HEADER
    by_sample = {}
    for r in rows[1:]:
        by_sample.setdefault(int(r[0]), []).append([float(v) for v in r[1:]])
    assert 1 <= len(by_sample) <= ReportParams.paths
    chosen = sorted(by_sample)
    with torch.no_grad():
        traj = result.problem.simulate(result.posterior.x[chosen])
    end = result.problem.frames.object_position(traj.final)[:, result.problem.source]
    for b, (index, path) in enumerate(sorted(by_sample.items())):
        steps = [int(p[0]) for p in path]
        assert steps == sorted(steps) and steps[0] == 0 and steps[-1] == result.problem.duration_steps
        assert path[0][2:] == pytest.approx(states[index, 0:3].tolist(), abs=1e-6)
        assert path[-1][2:] == pytest.approx(end[b].tolist(), abs=1e-6)


def test_rhat_is_one_for_runs_of_one_distribution_and_flags_runs_apart():
    """Rank-normalised R-hat of two runs: about 1 for 300 + 300 draws of one distribution (also heavy
    tailed, where the ranks matter), above the limit where one run's draws sit a deviation apart,
    and not defined for one run."""
    g = torch.Generator().manual_seed(3)
    values = torch.randn(600, 3, generator=g, dtype=torch.float64)
    values[:, 2] = values[:, 2] ** 3 * 100.0  # heavy tails and another unit
    run = torch.cat([torch.zeros(300, dtype=torch.long), torch.ones(300, dtype=torch.long)])
    same = rhat(values, run)
    assert torch.all((same > 0.99) & (same < 1.02)), same
    apart = values.clone()
    apart[300:, 0] += 1.0
    r = rhat(apart, run)
    assert r[0] > ReportParams.rhat_limit and torch.all(r[1:] < 1.02), r
    assert torch.isnan(rhat(values, torch.zeros(600, dtype=torch.long))).all()


def test_the_samples_come_from_independent_runs_of_half_the_particles():
    """Two runs of half the particles (odd: the first one more); n samples below ``particles``
    come from twice as many particles (at most ``particles``), n/2 of each run's, labelled;
    fewer than 40 particles: one run."""
    A = torch.eye(2, dtype=torch.float64)

    def res(x):
        return x @ A.T

    post = FakePosterior(2, lambda x: 0.5 * (res(x) ** 2).sum(-1), res)
    mode = Mode(torch.zeros(2, dtype=torch.float64), 0.0, 0.0, 0.0)
    smp = Sampler(SamplerParams(seed=0)).sample(post, [mode], 101)
    assert smp.stats["runs"] == 2 and smp.stats["particles"] == 202
    assert torch.bincount(smp.run).tolist() == [51, 50] and smp.x.shape == (101, 2)
    assert torch.unique(smp.x, dim=0).shape[0] > 90  # a subset of the particles, not copies
    fewer = Sampler(SamplerParams(particles=150))
    assert fewer.sample(post, [mode], 101).stats["particles"] == 150
    assert fewer.sample(post, [mode], 160).stats["particles"] == 160
    few = Sampler(SamplerParams(seed=0)).sample(post, [mode], 15)
    assert few.stats["runs"] == 1 and few.stats["particles"] == 30 and bool((few.run == 0).all())


def test_paths_are_drawn_by_weight_among_distinct_samples():
    x = torch.tensor([[0.0], [1.0], [1.0], [1.0], [2.0]], dtype=torch.float64)
    w = torch.tensor([0.5, 0.2, 0.2, 0.1, 0.0], dtype=torch.float64)
    smp = Samples(x=x, weights=w, log_density=torch.zeros(5), component=torch.zeros(5, dtype=torch.long),
                  mode_index=[0])
    assert path_samples(smp, count=8) == [0, 1]  # distinct samples only (first rows), never a weightless one
    assert path_samples(smp, count=2) == [0, 1]  # 2 draws, half the mass each
    assert len(path_samples(smp, count=1)) == 1


def test_samples_override_the_scene_and_zero_draws_none():
    assert solve(ramp_scene(samples=50), SolveParams(samples=0)).posterior is None


@pytest.mark.parametrize("kwargs, fragment", [
    ({"samples": -1}, "samples must be a non-negative integer"),
    ({"samples": 2.5}, "samples must be a non-negative integer"),
    ({"samples": 10, "optimizer": "lbfgs"}, "posterior samples need the default search"),
])
def test_bad_sample_settings_are_one_line_errors(kwargs, fragment):
    with pytest.raises(InferenceError) as info:
        solve(ramp_scene(), SolveParams(**kwargs))
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_a_posterior_with_no_free_parameter_is_refused():
    scene = ramp_scene(samples=10)
    scene = replace(scene, inference=replace(scene.inference, optimize=Optimize(
        position=False, orientation=False, linear_velocity=False, angular_velocity=False)))
    with pytest.raises(InferenceError) as info:
        solve(scene)
    assert "\n" not in str(info.value)


def test_cli_samples_flag(tmp_path):
    run = subprocess.run([sys.executable, "-m", "dejaview", "solve", str(SCENES / "ball_down_ramp.xml"), "-o",
                          str(tmp_path), "--samples", "100", "--quiet"], capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr
    weights, _ = read_csv(tmp_path / "posterior.csv")
    assert len(weights) == 100
    bad = subprocess.run([sys.executable, "-m", "dejaview", "solve", str(SCENES / "ball_down_ramp.xml"), "-o",
                          str(tmp_path / "bad"), "--samples", "-3", "--quiet"], capture_output=True, text=True,
                         timeout=600)
    assert bad.returncode != 0 and len(bad.stderr.strip().splitlines()) == 1 and "samples" in bad.stderr


@pytest.mark.parametrize("block, settings", [
    ("position", PosteriorSettings()),
    ("orientation", PosteriorSettings()),                 # Haar
    ("orientation", PosteriorSettings(tilt=0.4)),
    ("linear_velocity", PosteriorSettings()),             # uniform in the ball of the bound
    ("linear_velocity", PosteriorSettings(speed=0.7)),
    ("angular_velocity", PosteriorSettings(spin=3.0)),
])
def test_prior_draws_follow_the_normalised_prior_density(block, settings):
    """``log_prior_density`` is the normalised density of ``prior_draws``: importance weights
    p / g under a broad normal g average to 1, and the draws' density ranks like p."""
    from dejaview.backends.params import layout_from_scene
    from dejaview.inference.reference import log_prior_density, prior_draws

    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    free = {b: b == block for b in ("position", "orientation", "linear_velocity", "angular_velocity")}
    scene = replace(scene, inference=replace(scene.inference, optimize=Optimize(**free)))

    class P:
        layout = layout_from_scene(scene)

    P.settings = settings
    gen = torch.Generator().manual_seed(0)
    x = prior_draws(P, 20000, gen)
    assert torch.isfinite(log_prior_density(P, x)).all()
    sd = 3 * x.std(0)
    g = sd * torch.randn(400000, x.shape[1], generator=gen, dtype=torch.float64)
    log_g = (-0.5 * (g / sd) ** 2 - torch.log(sd * math.sqrt(2 * math.pi))).sum(-1)
    w = torch.exp(log_prior_density(P, g) - log_g)
    assert float(w.mean()) == pytest.approx(1.0, abs=0.03)


def test_a_thin_slab_in_eleven_parameters_keeps_the_priors_spread_along_it():
    """11 parameters with N(0, 1) priors, 6 random directions observed to 0.05 (the box thrown of
    the calibration bench: the end fixes 6 numbers, the prior the rest): 300 samples (the bench's
    count) spread along the 5 unobserved directions as the posterior does and across the thin
    ones too, from a search's mode 4 standard deviations off. Steps from each particle's nearest
    neighbours, every particle moved at once, kept 0.76 of the variance along the slab here (and
    without the difference steps 0.1-0.4: 90 % intervals held the truth 46 % of the time)."""
    gen = torch.Generator().manual_seed(0)
    p, m, sigma = 11, 6, 0.05
    a = torch.randn(m, p, generator=gen, dtype=torch.float64)
    prec = a.T @ a / sigma ** 2 + torch.eye(p, dtype=torch.float64)
    cov = torch.linalg.inv(prec)
    evals, evecs = torch.linalg.eigh(cov)  # ascending: the 6 thin directions first
    ratios = []
    for seed in range(4):
        truth = torch.randn(p, generator=gen, dtype=torch.float64)
        b = truth @ a.T + sigma * torch.randn(m, generator=gen, dtype=torch.float64)
        mean = cov @ (a.T @ b) / sigma ** 2

        def res(x, b=b):
            return torch.cat([(x @ a.T - b) / sigma, x], -1)  # observation, then the prior's residuals

        post = FakePosterior(p, lambda x, res=res: 0.5 * (res(x) ** 2).sum(-1), res)
        rough = mean + 4 * evecs[:, :m] @ torch.sqrt(evals[:m])  # a search's mode, 4 sd off across
        smp = Sampler(SamplerParams(seed=seed)).sample(post, [Mode(rough, 0.0, 0.0, 0.0)], 300)
        ratios.append(torch.diagonal(evecs.T @ torch.cov(smp.x.T) @ evecs) / evals)
    r = torch.stack(ratios).mean(0)
    assert 0.85 < float(r[m:].mean()) < 1.2, r  # along the slab
    assert 0.85 < float(r[:m].mean()) < 1.2, r  # across it



def test_the_population_move_rebalances_basins_the_particles_hold():
    """Two basins in 3 parameters holding 0.3 and 0.7 of the mass, the particles (drawn from each
    basin exactly) put 0.8 / 0.2 instead: the moves within a basin cannot mend that, the
    population move (a jump to where the other half's particles are, weighed by the target)
    does, and leaves each basin's shape as it is."""
    from dejaview.inference.reference import laplace_mixture
    from dejaview.inference.sampling import _SMC

    m = torch.tensor([[-1.0, 0.0, 0.0], [1.2, 0.3, -0.2]], dtype=torch.float64)
    s = torch.tensor([0.05, 0.1], dtype=torch.float64)
    w = torch.tensor([0.3, 0.7], dtype=torch.float64)

    def neg_log(x):  # the posterior itself: two normal basins, each normalised, weighted w
        z2 = (((x[:, None, :] - m[None]) / s[None, :, None]) ** 2).sum(-1)
        return -torch.logsumexp(torch.log(w) - 3 * torch.log(s) - 0.5 * z2, -1)

    post = FakePosterior(3, neg_log, lambda x: (x - m[0]) / s[0])
    q, _ = laplace_mixture(post, [Mode(m[0].clone(), float(neg_log(m[:1])), 0.0, 0.0)])
    gen = torch.Generator().manual_seed(0)
    n = 1000
    basin = (torch.arange(n) >= 800).long()  # 800 in the light basin, 200 in the heavy one
    x0 = m[basin] + s[basin, None] * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    shares = {}
    for kind in ("population_move", "random_walk_move"):
        smc = _SMC(post, q, n, 0, None, None, from_prior=False, params=SamplerParams())
        smc.x = x0.clone()
        smc.lr, smc.lq = smc.reference(smc.x), q.log_prob(smc.x)
        smc.lp = -neg_log(smc.x)
        smc.beta = 1.0
        for _ in range(40):
            getattr(smc, kind)()
        heavy = smc.x[:, 0] > 0.1
        shares[kind] = float(heavy.double().mean())
        if kind == "population_move":
            assert float(smc.x[heavy, 1].std()) == pytest.approx(0.1, rel=0.15)
            assert float(smc.x[~heavy, 1].std()) == pytest.approx(0.05, rel=0.15)
    assert shares["population_move"] == pytest.approx(0.7, abs=0.06), shares
    assert shares["random_walk_move"] < 0.3, shares  # the walk stays in its basin


def test_the_kernel_density_estimate_in_chunks_gives_the_same_samples():
    """``SamplerParams.kde_rows``: the population move's estimate 7 particles at a time (of some
    200 a half) draws the same samples, with the same weights, as all at once (round-off aside)."""
    m = torch.tensor([-1.0, 1.5], dtype=torch.float64)
    s = torch.tensor([0.05, 0.2], dtype=torch.float64)

    def neg_log(x):
        z = (x[:, :1] - m) / s
        return -torch.logsumexp(torch.log(0.5 / s) - 0.5 * z * z, -1)

    def res(x):
        k = ((x[:, :1] - m).abs() / s).argmin(-1)
        return (x[:, :1] - m[k, None]) / s[k, None]

    post = FakePosterior(1, neg_log, res)
    modes = [Mode(m[i:i + 1].clone(), float(neg_log(m[i:i + 1, None])), 0.0, 0.0) for i in range(2)]
    whole = Sampler(SamplerParams(seed=2)).sample(post, modes, 400)
    chunked = Sampler(SamplerParams(seed=2, kde_rows=7)).sample(post, modes, 400)
    assert torch.allclose(chunked.x, whole.x, rtol=1e-12, atol=0.0)
    assert torch.allclose(chunked.weights, whole.weights, rtol=1e-12, atol=0.0)


def test_solve_with_a_physics_prior_writes_the_physics(tmp_path):
    """``<physics-prior>``: the friction is inferred with the start; the CSV gains its columns by
    name, result.json its physics section, and the physics' prior is the CSV's spread."""
    from dejaview.scene import PhysicsPrior

    scene = ramp_scene(samples=100)
    scene = replace(scene, inference=replace(scene.inference, physics_prior=PhysicsPrior(friction=0.3)))
    result = solve(scene)
    assert result.problem.layout.names()[-1] == "physics.friction"
    paths = result.write(tmp_path)
    header = (tmp_path / "posterior.csv").read_text().splitlines()[0].split(",")
    assert header == list(CSV_HEADER) + ["friction", "restitution", "stiffness"]
    weights, states = read_csv(paths["posterior"])
    assert states.shape == (100, 13) and weights.sum() == pytest.approx(1.0)
    rows = np.loadtxt(paths["posterior"], delimiter=",", skiprows=1)
    assert np.allclose(rows[:, -2], 0.2) and np.all(rows[:, -3] > 0)  # restitution known, friction inferred
    assert rows[:, -3].std() > 0.01
    physics = json.loads(paths["result"].read_text())["physics"]
    assert physics["inferred"] == ["friction"] and physics["most_probable"]["restitution"] == pytest.approx(0.2)
    lo, hi = physics["intervals"]["friction"]["90%"]
    assert 0.5 * math.exp(-1.645 * 0.3) * 0.7 < lo < 0.5 < hi < 0.5 * math.exp(1.645 * 0.3) * 1.3


def test_local_optimisers_refuse_a_physics_prior():
    from dejaview.scene import PhysicsPrior

    scene = ramp_scene()
    scene = replace(scene, inference=replace(scene.inference, physics_prior=PhysicsPrior(friction=0.3)))
    with pytest.raises(InferenceError, match="physics-prior"):
        solve(scene, SolveParams(optimizer="lbfgs", iterations=2))


def test_a_backend_without_physics_columns_refuses_a_physics_prior():
    """Warp's layout has no physics columns: a physics prior is an error there, not ignored. Skipped
    where warp-lang is not installed (the warp extra, which scripts/setup installs)."""
    from dejaview.scene import PhysicsPrior

    pytest.importorskip("warp", reason="needs warp-lang")
    scene = ramp_scene()
    scene = replace(scene, inference=replace(scene.inference, physics_prior=PhysicsPrior(friction=0.3)))
    with pytest.raises(InferenceError, match="physics-prior.*warp"):
        solve(scene, SolveParams(iterations=2), backend="warp")


def test_a_heatmap_with_a_physics_prior_is_the_marginal_over_the_physics(tmp_path):
    """The posterior heatmap takes the physics columns (its samples carry them); the basins heatmap,
    whose per-cell optimisations have no prior, refuses a physics prior in one line."""
    from dejaview.heatmap import compute_heatmap
    from dejaview.scene import PhysicsPrior

    scene = ramp_scene()
    scene = replace(scene, inference=replace(scene.inference, physics_prior=PhysicsPrior(friction=0.3)))
    result = compute_heatmap(scene, cells=(4, 5), samples=2)
    assert float(result.probability.sum()) == pytest.approx(1.0)
    assert result.best.posterior.x.shape[1] == 3  # position x, y and the friction
    assert "physics" in result.best.settings
    with pytest.raises(InferenceError, match="physics-prior.*posterior heatmap"):
        compute_heatmap(scene, cells=(4, 5), samples=2, method="basins")


def test_each_run_estimates_the_evidence():
    """``stats["log_evidence"]``: each run's product of its tempering steps' mean weights estimates
    log of the integral of the unnormalised posterior density; on R(x) = A x - b it is
    -0.5 |r_min|^2 + (P/2) log 2 pi - 0.5 log det A^T A. ``result.json`` carries it in
    ``posterior.sampler``."""
    A = torch.tensor([[2.0, 0.5, 0.0], [0.0, 1.0, 0.3], [0.4, 0.0, 3.0], [0.1, 0.2, 0.1]], dtype=torch.float64)
    b = torch.tensor([1.0, -0.5, 0.7, 0.2], dtype=torch.float64)

    def res(x):
        return x @ A.T - b

    post = FakePosterior(3, lambda x: 0.5 * (res(x) ** 2).sum(-1), res)
    mean = torch.linalg.solve(A.T @ A, A.T @ b)
    exact = (-0.5 * float((res(mean[None]) ** 2).sum()) + 1.5 * math.log(2 * math.pi)
             - 0.5 * float(torch.logdet(A.T @ A)))
    smp = Sampler(SamplerParams(seed=1)).sample(post, [Mode(mean, 0.0, 0.0, 0.0)], 600)
    assert len(smp.stats["log_evidence"]) == 2
    for log_z in smp.stats["log_evidence"]:
        assert log_z == pytest.approx(exact, abs=0.25)
