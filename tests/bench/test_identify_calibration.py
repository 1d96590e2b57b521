"""The identify calibration bench (``bench/identify_calibration.py``, ``dejaview bench identify``):
tracked throws drawn from the scenes' priors, and the coverage it pools."""

from __future__ import annotations

import pytest
import torch
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.cli.bench import bench_module


def test_tracked_throws_are_seen_at_their_times_with_the_stated_noise():
    """A ball throw from the prior (physics drawn too), seen at the bench's five moments: each
    target is the simulated origin at its time plus noise of the scene's 3 mm."""
    from dejaview.backends.spheres import SpheresProblem
    from dejaview.inference.posterior import Posterior, PosteriorSettings

    module = bench_module("identify_calibration")
    scene = module.base_scene("ball")
    post = Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))
    assert post.layout.physics_names == ("friction", "restitution")
    truth = post.sample(1, torch.Generator().manual_seed(3))
    seen = module.tracked(scene, post, truth, module.TIMES["ball"], torch.Generator().manual_seed(4))
    targets = seen.inference.targets
    assert [t.time for t in targets] == list(module.TIMES["ball"])
    assert all(t.moving and t.orientation is None for t in targets)
    with torch.no_grad():
        st = post.problem.simulate(truth, record_every=1).states
    dt = post.problem.world.dt
    off = torch.stack([torch.tensor(t.position) - st.position[round(t.time / dt), 0, post.problem.source]
                       for t in targets])
    assert float(off.abs().max()) < 5 * 0.003  # the noise, not another moment
    assert float(off.abs().max()) > 0.0


def test_summary_pools_both_parameters_and_scores_the_errors():
    module = bench_module("identify_calibration")
    rows = [{"friction.cover50": True, "friction.cover90": True, "restitution.cover50": False,
             "restitution.cover90": True, "friction.error": 0.1, "restitution.error": -0.08,
             "friction.width90": 0.5, "restitution.width90": 0.1, "seconds": 2.0},
            {"friction.cover50": False, "friction.cover90": True, "restitution.cover50": False,
             "restitution.cover90": False, "friction.error": -0.3, "restitution.error": 0.01,
             "friction.width90": 0.7, "restitution.width90": 0.05, "seconds": 4.0}]
    s = module.summarize(rows)
    assert s["cover50"] == 0.25 and s["cover90"] == 0.75
    assert s["friction_within_15pct"] == 0.5 and s["restitution_within_0.05"] == 0.5
    assert s["seconds"] == 3.0
    assert module.verdict(s) == "NOT calibrated"


def test_cli_rejects_an_unknown_kind():
    result = CliRunner().invoke(cli, ["bench", "identify", "--kinds", "moon"])
    assert result.exit_code != 0 and "moon" in result.output


@pytest.mark.slow
def test_one_truth_identifies_a_physics_inside_the_prior():
    row = bench_module("identify_calibration").run_case("ball", 0)
    assert 0.0 < row["restitution.true"] <= 1.0 and row["friction.true"] > 0.0
    assert abs(row["restitution.error"]) < 0.1
    assert row["restitution.width90"] > 0.0 and "grid" in row["intervals_from"]
