"""The amortised answer beside the sampler's (``bench/amortised.py``'s ``compare``, ``dejaview bench
amortised-vs-sampler``): its two-sample distances, and one small run's table."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from dejaview.cli.bench import bench_module

SCENES = Path(__file__).resolve().parents[2] / "examples" / "scenes"


def uniform(n: int) -> torch.Tensor:
    return torch.full((n,), 1.0 / n, dtype=torch.float64)


def test_distances_are_zero_for_the_same_samples_and_grow_with_a_shift():
    distances = bench_module("amortised").sample_distances
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(300, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 10.0, 0.01])
    same = distances(a, uniform(300), a.clone(), uniform(300))
    assert same["ks"] == [0.0, 0.0, 0.0] and same["energy"] == 0.0
    b = torch.randn(200, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 10.0, 0.01])
    near = distances(a, uniform(300), b, uniform(200))
    far = distances(a, uniform(300), b + torch.tensor([1.0, 0.0, 0.0]), uniform(200))
    assert all(math.isfinite(v) for v in near["ks"] + [near["energy"], far["energy"]])
    assert far["ks"][0] > 0.3 > near["ks"][0] and far["ks"][1:] == near["ks"][1:]
    assert far["energy"] > 2 * near["energy"] > 0


def test_ks_is_scipys_for_equal_weights_and_weights_count_as_repeats():
    from scipy.stats import ks_2samp

    distances = bench_module("amortised").sample_distances
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(50, 1, generator=gen, dtype=torch.float64)
    b = torch.randn(70, 1, generator=gen, dtype=torch.float64) + 0.3
    got = distances(a, uniform(50), b, uniform(70))["ks"][0]
    assert got == pytest.approx(ks_2samp(a[:, 0].numpy(), b[:, 0].numpy()).statistic, abs=1e-12)
    # a sample weighted 1/2 is the same set as that sample drawn twice
    x = torch.tensor([[0.0], [1.0], [2.0]], dtype=torch.float64)
    w = torch.tensor([0.5, 0.25, 0.25], dtype=torch.float64)
    twice = torch.tensor([[0.0], [0.0], [1.0], [2.0]], dtype=torch.float64)
    out = distances(x, w, twice, uniform(4))
    assert out["ks"] == [0.0] and out["energy"] == pytest.approx(0.0, abs=1e-7)


def test_a_small_comparison_prints_both_answers_per_parameter():
    """ball_down_ramp (the start's x-y free) from a tiny flow, 20 samples each (two sampler runs): a
    row per parameter with both medians inside their 90 % intervals, KS statistics in [0, 1],
    finite distances."""
    pytest.importorskip("zuko", reason="the amortised extra (pip install 'dejaview[amortised]')")
    from dejaview.inference.amortised import train
    from dejaview.inference.params import TrainParams
    from dejaview.scene import Scene

    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    model = train(scene, TrainParams(simulations=400, epochs=15, patience=5, transforms=2, hidden=(32, 32),
                                     batch=128, lr=3e-3))
    lines = []
    rows = bench_module("amortised").compare(print_fn=lines.append, scenes=(scene,), samples=20, model=model)
    names = [r["parameter"] for r in rows]
    assert names == ["position.x", "position.y"]
    for r in rows:
        for who in ("amortised", "sampler"):
            assert r[f"{who}_lo90"] <= r[f"{who}_median"] <= r[f"{who}_hi90"]
            assert isinstance(r[f"{who}_rollouts"], int) and r[f"{who}_rollouts"] > 0
        assert 0.0 <= r["ks"] <= 1.0 and 0.0 <= r["ks_runs"] <= 1.0
        assert math.isfinite(r["energy"]) and r["energy"] >= 0 and math.isfinite(r["energy_runs"])
        assert math.isfinite(r["k_hat"]) and r["fitted"] == (r["k_hat"] <= 0.7)
        assert r["fallback"] == (None if r["fitted"] else "sampler") and r["train_s"] is None
    assert len({r["energy"] for r in rows}) == 1  # one joint distance per scene
    text = "\n".join(lines)
    assert "Pareto k-hat" in text and "energy distance" in text and all(n in text for n in names)
