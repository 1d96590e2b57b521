"""Heatmap weighting: deduplication, basin levels, the weight formula, cell probabilities."""

import math

import pytest
import torch

from dejaview.heatmap import cell_boxes
from dejaview.heatmap.search import split_cells
from dejaview.heatmap.weighting import (cell_probability, deduplicate, entropy_bits, log_weights,
                                        perturbation_directions, robustness_levels)


def starts(n, **overrides):
    s = {"position": torch.zeros(n, 3), "orientation": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
         "linear_velocity": torch.zeros(n, 3), "angular_velocity": torch.zeros(n, 3)}
    s.update(overrides)
    return s


def test_duplicates_within_a_cell_count_once_and_keep_the_lowest_loss():
    v = torch.tensor([[1.0, 0, 0], [1.01, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
    cell = torch.tensor([0, 0, 0, 1])
    loss = torch.tensor([0.2, 0.1, 0.3, 0.5])
    kept = deduplicate(cell, loss, starts(4, linear_velocity=v), velocity_tol=0.05)
    # 0 and 1 are one solution (1 has the lower loss); 2 differs; 3 is alone in cell 1
    assert kept.tolist() == [1, 2, 3]


def test_same_velocity_from_different_positions_or_spins_is_not_a_duplicate():
    pos = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [0.0, 0, 0]])
    spin = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [0.0, 0, 3.0]])
    kept = deduplicate(torch.zeros(3, dtype=torch.long), torch.tensor([0.1, 0.2, 0.3]),
                       starts(3, position=pos, angular_velocity=spin))
    assert kept.tolist() == [0, 1, 2]


def test_non_finite_losses_are_dropped():
    kept = deduplicate(torch.tensor([0, 1]), torch.tensor([math.nan, 0.1]),
                       starts(2, linear_velocity=torch.tensor([[0.0, 0, 0], [5.0, 0, 0]])))
    assert kept.tolist() == [1]


def test_basin_level_counts_consecutive_radii_held_by_half_the_directions():
    sigma = 0.02
    loss = torch.tensor([0.01, 0.01, 0.01])
    ok, bad = 0.02, 0.5
    p = torch.full((3, 3, 4), ok)
    p[1, 1, :3] = bad  # breaks at the second radius (3 of 4 directions fail)
    p[2, 0, :2] = bad  # half the directions hold at the first radius: still holds
    p[2, 1, :] = bad   # ... and breaks at the second
    p[2, 2, :] = ok    # holding again further out does not count
    assert robustness_levels(loss, p, sigma).tolist() == [3, 1, 1]
    p[0, 0, 0] = math.nan
    p[0, 0, 1:3] = bad
    assert robustness_levels(loss, p, sigma)[0] == 0


def test_weight_formula():
    loss = torch.tensor([0.0, 0.02, 0.0], dtype=torch.float64)
    level = torch.tensor([5, 5, 0])
    logw = log_weights(loss, level, radii=5, sigma=0.02)
    assert logw[0].item() == pytest.approx(0.0)
    assert logw[1].item() == pytest.approx(-0.5)  # one sigma: exp(-1/2)
    assert logw[2].item() == pytest.approx(math.log(1 / 6))


def test_cell_probability_sums_to_one_and_adds_solutions_of_a_cell():
    cell = torch.tensor([0, 0, 2])
    logw = torch.log(torch.tensor([1.0, 1.0, 2.0], dtype=torch.float64))
    p = cell_probability(cell, logw, 4)
    assert p.tolist() == pytest.approx([0.5, 0.0, 0.5, 0.0])
    # far-off losses (weights that underflow) still give a distribution
    p = cell_probability(torch.tensor([1, 3]), torch.tensor([-5000.0, -5001.0], dtype=torch.float64), 4)
    assert p.sum().item() == pytest.approx(1.0)
    assert p[1] > p[3] > 0


def test_entropy_of_uniform_and_peaked():
    assert entropy_bits(torch.full((16,), 1 / 16)) == pytest.approx(4.0)
    assert entropy_bits(torch.tensor([1.0, 0, 0, 0])) == pytest.approx(0.0)


def test_perturbation_directions_are_unit_and_leave_spin_alone_unless_asked():
    g = torch.Generator().manual_seed(0)
    d = perturbation_directions(5, 8, spin=False, generator=g)
    assert d.shape == (5, 8, 6)
    assert torch.allclose(d.norm(dim=-1), torch.ones(5, 8, dtype=d.dtype))
    assert (d[..., 3:] == 0).all()
    d = perturbation_directions(5, 8, spin=True, generator=g)
    assert (d[..., 3:] != 0).any()


def test_cells_cover_the_area_row_by_row():
    lo, hi = torch.tensor([-1.0, 0.0, 0.5]), torch.tensor([1.0, 1.0, 0.7])
    a, b = cell_boxes(lo, hi, 4, 2)
    assert a.shape == (8, 3)
    assert a[0].tolist() == pytest.approx([-1.0, 0.0, 0.5])
    assert b[0].tolist() == pytest.approx([-0.5, 0.5, 0.7])
    assert a[5].tolist() == pytest.approx([-0.5, 0.5, 0.5])  # cell 5 = (i=1, j=1)
    assert b[-1].tolist() == pytest.approx(hi.tolist())


@pytest.mark.parametrize("cells,samples,batch,workers,expect", [
    (16, 4, 1024, 1, 1), (256, 4, 1024, 1, 1), (256, 4, 1024, 2, 2), (256, 4, 100, 1, 11),
    (3, 4, 1024, 8, 3), (10, 4, 1, 1, 10)])
def test_split_cells(cells, samples, batch, workers, expect):
    chunks = split_cells(cells, samples, batch, workers)
    assert len(chunks) == expect
    assert sum(chunks, []) == list(range(cells))
    assert all(len(c) * samples <= max(batch, samples) for c in chunks)
