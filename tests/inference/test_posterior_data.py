"""The posterior for analysis tools (``dejaview.inference.posterior_data``): named arrays, the
DataFrame of posterior.csv, ArviZ's InferenceData with the sampler's runs as chains, and
posterior.nc, whose R-hat and ESS in ArviZ are the ones result.json reports."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

az = pytest.importorskip("arviz")
pd = pytest.importorskip("pandas")
from scipy.special import ndtri  # noqa: E402
from scipy.stats import rankdata  # noqa: E402

from dejaview.inference import solve  # noqa: E402
from dejaview.inference.posterior_data import variable_of  # noqa: E402
from dejaview.inference.posterior_report import CSV_HEADER, ess_bulk, physical, rhat  # noqa: E402
from dejaview.scene import PosteriorRequest, Scene  # noqa: E402

SCENES = Path(__file__).resolve().parents[2] / "examples" / "scenes"


def ramp_scene(samples: int) -> Scene:
    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    return replace(scene, inference=replace(scene.inference, posterior=PosteriorRequest(samples=samples)))


@pytest.fixture(scope="module")
def ramp():
    """The ramp's posterior, 200 samples from two runs of 100, and its result set."""
    return solve(ramp_scene(200))


@pytest.fixture(scope="module")
def written(ramp, tmp_path_factory):
    out = tmp_path_factory.mktemp("ramp")
    ramp.write(out)
    return out


def test_posterior_nc_rhat_and_ess_are_the_reported_ones(ramp, written):
    idata = az.from_netcdf(written / "posterior.nc")
    intervals = json.loads((written / "result.json").read_text())["posterior"]["intervals"]
    assert list(intervals) == ramp.problem.layout.names() == ["position.x", "position.y"]
    ess = az.ess(idata, method="bulk")
    split_rhat = az.rhat(idata)  # ArviZ's default: rank-normalised, split, bulk and tail
    draws = np.concatenate([idata.posterior["position"].values[c] for c in range(2)])  # (200, 2), run order
    for j, (name, iv) in enumerate(intervals.items()):
        var, sel = variable_of(name)
        # ESS: ArviZ's bulk ESS is the one reported, to rounding
        assert iv["ess"] == pytest.approx(float(ess[var].sel(sel)), rel=1e-9)
        # R-hat, exactly: ArviZ's R-hat formula over the runs unsplit (method="identity") of the
        # pooled draws' normal scores (Blom's ranks, no ties among these samples)
        column = draws[:, j]
        assert np.unique(column).size == column.size
        z = ndtri((rankdata(column) - 0.375) / (column.size + 0.25)).reshape(2, -1)
        assert iv["rhat"] == pytest.approx(float(az.rhat(z, method="identity")), abs=1e-12)
        # ... and ArviZ's default R-hat, which also splits each run in two and takes the folded
        # draws' too: within 0.02 where the runs agree (docs/inference.md)
        assert abs(iv["rhat"] - float(split_rhat[var].sel(sel))) < 0.02


def test_both_rhats_flag_runs_that_disagree(ramp):
    """One run moved off by two standard deviations: DejaView's and ArviZ's R-hat both over 1.1."""
    x = ramp.posterior.x.clone()
    second = ramp.posterior.run == 1
    x[second, 0] += 2 * x[:, 0].std()
    moved = replace(ramp, posterior=replace(ramp.posterior, x=x))
    ours = rhat(physical(moved.problem.layout, x), moved.posterior.run)
    theirs = az.rhat(moved.to_arviz())["position"].sel(position_axis="x")
    assert float(ours[0]) > 1.1 and float(theirs) > 1.1


def test_to_arviz_has_the_runs_as_chains(ramp):
    idata = ramp.to_arviz()
    post, stats = idata.posterior, idata.sample_stats
    assert dict(post.sizes) == {"chain": 2, "draw": 100, "position_axis": 2}
    assert list(post["position_axis"].values) == ["x", "y"] and post["position"].attrs["units"] == "m"
    values = physical(ramp.problem.layout, ramp.posterior.x).numpy()
    lp = ramp.posterior.log_density.numpy()
    for chain in range(2):
        rows = (ramp.posterior.run == chain).numpy()
        np.testing.assert_array_equal(post["position"].values[chain], values[rows])
        np.testing.assert_array_equal(stats["lp"].values[chain], lp[rows])
    assert "weight" not in stats  # equal weights: nothing to say
    assert post.attrs["inference_library"] == "dejaview" and post.attrs["source"] == "ball"


def test_unequal_weights_go_to_sample_stats(ramp):
    w = torch.linspace(1.0, 2.0, 200, dtype=torch.float64)
    weighted = replace(ramp, posterior=replace(ramp.posterior, weights=w / w.sum()))
    stats = weighted.to_arviz().sample_stats
    np.testing.assert_allclose(stats["weight"].values.ravel(), (w / w.sum()).numpy())


def test_frame_columns_and_values_are_the_csv(ramp, written):
    df = ramp.posterior_frame()
    csv = pd.read_csv(written / "posterior.csv")
    assert list(df.columns) == list(csv.columns) == list(CSV_HEADER)
    pd.testing.assert_frame_equal(df, csv, check_exact=True)


def test_arrays_are_the_parameters_in_physical_units(ramp):
    arrays = ramp.posterior_arrays()
    assert list(arrays) == ["position.x", "position.y", "weight", "run", "log_density"]
    values = physical(ramp.problem.layout, ramp.posterior.x).numpy()
    np.testing.assert_array_equal(np.stack([arrays["position.x"], arrays["position.y"]], -1), values)
    np.testing.assert_array_equal(arrays["run"], ramp.posterior.run.numpy())
    assert arrays["weight"].sum() == pytest.approx(1.0)


@pytest.mark.parametrize("sizes", [(50, 50), (51, 50), (7, 6, 6)])
def test_ess_bulk_is_arviz_s(sizes):
    """On draws with ties (duplicated particles) and runs of unequal size: the chains are cut to
    the shortest run, as posterior.nc's are."""
    gen = np.random.default_rng(sum(sizes))
    runs = [gen.normal(0.3 * k, 1.0, (n, 3)).round(1) for k, n in enumerate(sizes)]
    values = torch.tensor(np.concatenate(runs))
    run = torch.cat([torch.full((n,), k) for k, n in enumerate(sizes)])
    k = min(sizes)
    chains = np.stack([r[:k] for r in runs])
    ours = ess_bulk(values, run)
    for j in range(3):
        assert float(ours[j]) == pytest.approx(float(az.ess(chains[:, :, j], method="bulk")), rel=1e-9)


def test_without_arviz_the_solve_writes_posterior_csv_alone(ramp, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "arviz", None)  # import arviz raises ImportError
    paths = ramp.write(tmp_path)
    assert (tmp_path / "posterior.csv").exists() and not (tmp_path / "posterior.nc").exists()
    assert "posterior_nc" not in paths
    with pytest.raises(ImportError, match=r"dejaview\[analysis\]"):
        ramp.to_arviz()


def test_cli_solve_writes_posterior_nc_and_skips_it_silently_without_arviz(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from dejaview.cli import cli

    scene = str(SCENES / "ball_down_ramp.xml")
    with_arviz = CliRunner().invoke(cli, ["solve", scene, "-o", str(tmp_path / "a"), "--samples", "40"])
    assert with_arviz.exit_code == 0, with_arviz.output
    assert az.from_netcdf(tmp_path / "a" / "posterior.nc").posterior.sizes["chain"] == 2
    monkeypatch.setitem(sys.modules, "arviz", None)
    without = CliRunner().invoke(cli, ["solve", scene, "-o", str(tmp_path / "b"), "--samples", "40"])
    assert without.exit_code == 0, without.output
    assert (tmp_path / "b" / "posterior.csv").exists() and not (tmp_path / "b" / "posterior.nc").exists()
    assert "arviz" not in without.output.lower() and "netcdf" not in without.output.lower()


def test_inferred_physics_are_scalar_variables_and_csv_columns(tmp_path):
    """box_throw_1: everything free and the floor's friction and restitution inferred (no solve:
    samples drawn at random in the layout)."""
    from dejaview.inference import Posterior
    from dejaview.inference.posterior_data import frame, to_inference_data
    from dejaview.inference.posterior_report import PHYSICS_COLUMNS, write_csv
    from dejaview.inference.sampling import PosteriorSamples

    layout = Posterior.from_scene(Scene.from_xml(SCENES / "box_throw_1.xml")).layout
    gen = torch.Generator().manual_seed(0)
    n = 30
    samples = PosteriorSamples(x=0.3 * torch.randn(n, layout.size, generator=gen, dtype=torch.float64),
                               weights=torch.full((n,), 1.0 / n, dtype=torch.float64),
                               log_density=torch.randn(n, generator=gen, dtype=torch.float64),
                               component=torch.zeros(n, dtype=torch.long), mode_index=[0],
                               run=torch.arange(n) % 2)
    post = to_inference_data(samples, layout).posterior
    assert set(post.data_vars) == {"position", "orientation", "linear_velocity", "angular_velocity",
                                   "friction", "restitution"}
    assert post["friction"].dims == ("chain", "draw") and post["friction"].attrs["units"] == "1"
    values = physical(layout, samples.x).numpy()
    for j, name in enumerate(layout.names()):
        var, sel = variable_of(name)
        np.testing.assert_array_equal(post[var].sel(sel).values, np.stack([values[0::2, j], values[1::2, j]]))
    df = frame(samples, layout)
    csv = pd.read_csv(write_csv(tmp_path / "posterior.csv", samples, layout))
    assert list(df.columns) == list(CSV_HEADER + PHYSICS_COLUMNS)
    pd.testing.assert_frame_equal(df, csv, check_exact=True)
