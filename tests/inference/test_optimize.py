"""The one optimisation loop (``dejaview.inference.optimize``) on cheap analytic objectives.

No simulation here: each objective is a batched ``value_and_grad(x (K, P), mode)
-> (losses (K,), gradients (K, P))`` in closed form, so every test runs in
milliseconds and pins the loop's own behaviour (optimisers, progress, restarts,
cancellation, tolerance, NaN handling) apart from the physics.
"""

import math

import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.inference import OPTIMIZERS, Progress, make_optimizer, optimize

F64 = dict(dtype=torch.float64)
# GD's step must stay below 1 / curvature of these objectives (the default suits solve's scaling)
LR = {"gd": 0.05}


def quadratic(centre=(0.3, -0.2, 0.5), curvature=(1.0, 2.0, 4.0)):
    """Batched f(x) = sum_i a_i (x_i - c_i)^2, minimum 0 at c; mode is ignored."""
    c = torch.tensor(centre, **F64)
    a = torch.tensor(curvature, **F64)

    def value_and_grad(x, mode):
        d = x - c
        return (a * d * d).sum(-1), 2.0 * a * d

    return value_and_grad


def rosenbrock(x, mode=None):
    """Batched 2-D Rosenbrock (a curved valley), minimum 0 at (1, 1)."""
    u, v = x[:, 0], x[:, 1]
    value = (1 - u) ** 2 + 100 * (v - u * u) ** 2
    grad = torch.stack([-2 * (1 - u) - 400 * u * (v - u * u), 200 * (v - u * u)], -1)
    return value, grad


def loss_of(value_and_grad, x):
    return value_and_grad(x.reshape(1, -1), "reverse")[0].item()


# ------------------------------------------------------------------ optimisers
@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_every_optimizer_reduces_a_quadratic(optimizer):
    """Each optimiser (GD with a stable step) drives a well-conditioned bowl
    (curvatures 1..4) to 1e-4 of its starting loss in 60 iterations."""
    f = quadratic()
    x0 = torch.zeros(1, 3, **F64)
    start = loss_of(f, x0[0])
    res = optimize(f, x0, optimizer=optimizer, iterations=60, lr=LR.get(optimizer))
    assert res.loss < 1e-4 * start
    assert loss_of(f, res.x) == pytest.approx(res.loss, rel=1e-12, abs=1e-300)


@pytest.mark.parametrize("optimizer", ["lbfgs", "bfgs"])
def test_quasi_newton_solves_rosenbrock(optimizer):
    """L-BFGS and BFGS (strong-Wolfe line search) follow Rosenbrock's curved valley to
    the minimum (1, 1) from the classic start (-1.2, 1) in at most 100 iterations."""
    x0 = torch.tensor([[-1.2, 1.0]], **F64)
    res = optimize(rosenbrock, x0, optimizer=optimizer, iterations=100)
    assert res.loss < 1e-8
    assert torch.allclose(res.x, torch.tensor([1.0, 1.0], **F64), atol=1e-4)


@pytest.mark.parametrize("optimizer", ["gd", "adam"])
def test_first_order_methods_make_progress_on_rosenbrock(optimizer):
    """GD and Adam are slow in the valley, but they must still go down from 24.2."""
    x0 = torch.tensor([[-1.2, 1.0]], **F64)
    lr = 1e-3 if optimizer == "gd" else 0.05  # GD's default 0.05 diverges on curvature ~1000
    res = optimize(rosenbrock, x0, optimizer=optimizer, iterations=100, lr=lr)
    assert res.loss < 0.5 * rosenbrock(x0)[0].item()


@pytest.mark.parametrize("num_params", [3, 12, 40])
def test_bfgs_history_holds_at_least_every_parameter(num_params):
    """``bfgs`` is L-BFGS whose memory is at least P pairs (a full-rank inverse Hessian
    after P steps); ``lbfgs`` keeps the usual 10."""
    x = torch.nn.Parameter(torch.zeros(1, num_params, **F64))
    bfgs = make_optimizer("bfgs", [x], num_params)
    lbfgs = make_optimizer("lbfgs", [x], num_params)
    assert isinstance(bfgs, torch.optim.LBFGS)
    assert bfgs.defaults["history_size"] >= num_params
    assert lbfgs.defaults["history_size"] == 10


def test_unknown_optimizer_and_gradient_mode_are_refused():
    """The loop resolves names in one place and refuses others with one line naming them."""
    f = quadratic()
    x0 = torch.zeros(1, 3, **F64)
    with pytest.raises(InferenceError, match="newton") as err:
        optimize(f, x0, optimizer="newton")
    assert "\n" not in str(err.value)
    with pytest.raises(InferenceError, match="sideways"):
        optimize(f, x0, gradient="sideways")
    for bad in (0, -1, True, 2.5):
        with pytest.raises(InferenceError, match="iterations"):
            optimize(f, x0, iterations=bad)


# -------------------------------------------------------------------- progress
@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_callback_gets_one_progress_per_iteration_with_non_increasing_best(optimizer):
    """The callback (what the CLI's progress bar and the server use) is called exactly
    once per iteration, in order, with the same records the result keeps; the best loss
    never goes up, and it is never above the loss reported in the same iteration."""
    seen = []
    res = optimize(rosenbrock, torch.tensor([[-1.2, 1.0]], **F64), optimizer=optimizer,
                   iterations=25, lr=1e-3 if optimizer == "gd" else None, callback=seen.append)
    assert len(seen) == 25
    assert all(isinstance(p, Progress) for p in seen)
    assert [p.iteration for p in seen] == list(range(25))
    assert seen == res.history
    best = [p.best_loss for p in seen]
    assert all(b1 <= b0 for b0, b1 in zip(best, best[1:]))
    assert all(p.best_loss <= p.loss for p in seen)
    assert res.loss == best[-1]
    elapsed = [p.elapsed_s for p in seen]
    assert all(e1 >= e0 for e0, e1 in zip(elapsed, elapsed[1:]))
    assert all(p.duration_s >= 0 for p in seen)
    evaluations = [p.evaluations for p in seen]
    assert evaluations[0] >= 1 and all(e1 >= e0 for e0, e1 in zip(evaluations, evaluations[1:]))


# -------------------------------------------------------------------- restarts
def plateau_with_a_well(x, mode=None):
    """A flat plateau (loss 1, zero gradient) with one bowl around x = (2, 2) of radius 1.

    Gradient descent started on the plateau can never leave it: only a restart that
    lands in the bowl makes progress. The bowl's floor is 0 at (2, 2).
    """
    d = x - 2.0
    r2 = (d * d).sum(-1)
    inside = r2 < 1.0
    value = torch.where(inside, r2, torch.ones_like(r2))
    grad = torch.where(inside[:, None], 2.0 * d, torch.zeros_like(d))
    return value, grad


def sample_box(lo, hi):
    """Restart sampler: uniform in [lo, hi]^2."""

    def sample(n, gen):
        return lo + (hi - lo) * torch.rand(n, 2, generator=gen, **F64)

    return sample


def test_restarts_happen_are_recorded_and_the_global_best_is_kept():
    """With epsilon = 1 and patience = 1 a stalled candidate restarts from a fresh draw
    (flagged ``restarted`` in that iteration's Progress); the best found before a
    restart survives it, though the restarted candidate itself then sits elsewhere."""
    x0 = torch.tensor([[-3.0, -3.0]], **F64)  # on the plateau
    # lr 0.5 jumps to the bottom of the bowl in one step; there it stalls and restarts again
    res = optimize(plateau_with_a_well, x0, optimizer="gd", iterations=40, lr=0.5, epsilon=1.0,
                   patience=1, sample=sample_box(0.0, 4.0), seed=3)
    flags = [p.restarted for p in res.history]
    assert sum(flags) >= 3
    assert res.loss == 0.0  # some restart found the bowl, and GD went down it
    assert res.loss == min(p.best_loss for p in res.history) == res.history[-1].best_loss
    assert loss_of(plateau_with_a_well, res.x) == pytest.approx(res.loss)
    # a restart after the bowl was found moves the candidate away; the best is unchanged
    found = next(i for i, p in enumerate(res.history) if p.best_loss < 1.0)
    later = [p for p in res.history[found + 1:] if p.loss > p.best_loss]
    assert later, "expected a restart to leave the best point after it was found"


def test_no_restarts_without_epsilon():
    """epsilon = 0 (the default): a candidate stuck on the plateau stays there."""
    x0 = torch.tensor([[-3.0, -3.0]], **F64)
    res = optimize(plateau_with_a_well, x0, optimizer="gd", iterations=20, patience=1,
                   sample=sample_box(0.0, 4.0))
    assert not any(p.restarted for p in res.history)
    assert res.loss == 1.0
    assert torch.equal(res.x, x0[0])


def egg_crate(x, mode=None):
    """A bowl 2 |x|^2 under ripples 0.1 (1 - cos(2 pi x_i / 0.25)): a local minimum
    near every point of the 0.25 grid; the global one is 0 at the origin."""
    w = 2.0 * math.pi / 0.25
    value = 2.0 * (x * x).sum(-1) + 0.1 * (1.0 - torch.cos(w * x)).sum(-1)
    grad = 4.0 * x + 0.1 * w * torch.sin(w * x)
    return value, grad


def test_stalled_candidates_hop_from_their_best_into_neighbouring_basins():
    """With epsilon ~0 a stalled candidate never draws a fresh guess (the sampler would
    fail the test) but hops: it restarts near its best point, and hop by hop it walks
    down the ripples from its start at (0.75, 0.75), where GD alone stalls at a loss
    of 0.94, to the basin of the origin or one next to it (loss 0.12)."""

    def no_fresh_draws(n, gen):
        raise AssertionError("epsilon ~0 must not draw fresh guesses")

    x0 = torch.tensor([[0.75, 0.75]], **F64)
    stuck = optimize(egg_crate, x0, optimizer="gd", iterations=300, lr=0.01, patience=3)
    assert stuck.loss > 0.9 and not any(p.restarted for p in stuck.history)
    for seed in range(3):
        res = optimize(egg_crate, x0, optimizer="gd", iterations=300, lr=0.01, patience=3,
                       epsilon=1e-12, sample=no_fresh_draws, seed=seed)
        assert sum(p.restarted for p in res.history) >= 3
        assert res.loss < 0.15
        assert loss_of(egg_crate, res.x) == pytest.approx(res.loss, abs=1e-12)


def creeping_slope(x, mode=None):
    """A shallow slope whose GD steps shrink the loss by 1e-4 relative per iteration
    (loss 1 + 1e-4 x_0 from x_0 = 0 going negative): progress too small to count."""
    value = 1.0 + 1e-4 * x[:, 0] + 0.0 * x[:, 1]
    grad = torch.zeros_like(x)
    grad[:, 0] = 1e-4
    return value, grad


def test_creeping_counts_as_a_stall_and_triggers_restarts():
    """A candidate whose best loss falls by less than LocalParams.stall_ratio per iteration is
    stalled: with patience 3 and epsilon 1 it restarts. Without the ratio (every
    decrease an improvement) it would creep on and never restart."""
    from dejaview.inference.params import LocalParams

    x0 = torch.zeros(1, 2, **F64)
    res = optimize(creeping_slope, x0, optimizer="gd", iterations=12, lr=1.0, epsilon=1.0,
                   patience=3, sample=sample_box(-1.0, 0.0), seed=0)
    losses = [p.best_loss for p in res.history]
    assert all(b < a for a, b in zip(losses, losses[1:4]))  # it does go down...
    assert (losses[0] - losses[3]) / losses[0] < LocalParams().stall_ratio  # ...by too little
    assert any(p.restarted for p in res.history[:5])


def test_restarts_need_a_sampler():
    with pytest.raises(InferenceError, match="sample"):
        optimize(quadratic(), torch.zeros(1, 3, **F64), epsilon=0.5)


# ---------------------------------------------------------- stopping criteria
@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_should_stop_stops_within_one_iteration(optimizer):
    """Cancellation (the server's stop button) is polled before every iteration: once
    it says stop, no further iteration starts, and the result says it was stopped."""
    progress = []

    def should_stop():
        return len(progress) >= 4

    res = optimize(rosenbrock, torch.tensor([[-1.2, 1.0]], **F64), optimizer=optimizer,
                   iterations=50, lr=1e-3 if optimizer == "gd" else None, callback=progress.append,
                   should_stop=should_stop)
    assert len(res.history) == 4
    assert res.stopped
    assert math.isfinite(res.loss)


def test_should_stop_before_the_first_iteration_evaluates_nothing():
    calls = []

    def f(x, mode):
        calls.append(1)
        return quadratic()(x, mode)

    res = optimize(f, torch.zeros(1, 3, **F64), iterations=10, should_stop=lambda: True)
    assert res.stopped and res.history == [] and calls == []


@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_tolerance_stops_at_the_first_iteration_that_reaches_it(optimizer):
    """``tolerance`` ends the run as soon as the best loss is at or below it (it is not a
    cancellation: ``stopped`` stays False)."""
    f = quadratic()
    res = optimize(f, torch.zeros(1, 3, **F64), optimizer=optimizer, iterations=200, tolerance=1e-3,
                   lr=LR.get(optimizer))
    assert len(res.history) < 200
    assert res.history[-1].best_loss <= 1e-3
    assert all(p.best_loss > 1e-3 for p in res.history[:-1])
    assert not res.stopped


# ---------------------------------------------------------------- NaN handling
def nan_for_negative_first_coordinate(x, mode=None):
    """The quadratic, but NaN (value and gradient) for candidates with x_0 < 0: as a
    rollout that blew up would give for one candidate of a multistart batch."""
    value, grad = quadratic()(x, mode)
    bad = x[:, 0] < 0
    value = torch.where(bad, torch.full_like(value, math.nan), value)
    grad = torch.where(bad[:, None], torch.full_like(grad, math.nan), grad)
    return value, grad


@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_a_nan_candidate_does_not_poison_the_others(optimizer):
    """Candidates of a batch are independent: a candidate whose loss is NaN (counted as a
    huge loss, zero gradient) must not stop its neighbour from converging, nor be
    reported as the best. For GD and Adam (elementwise updates) the healthy candidate
    follows exactly the path it follows alone, and so does it for L-BFGS and BFGS, which
    give each candidate an optimiser of its own."""
    good = torch.tensor([[0.9, 0.1, 0.2]], **F64)
    batch = torch.cat([good, torch.tensor([[-1.0, 0.0, 0.0]], **F64)])
    res = optimize(nan_for_negative_first_coordinate, batch, optimizer=optimizer, iterations=60,
                   lr=LR.get(optimizer))
    assert res.best_index == 0
    assert torch.isfinite(res.x).all()
    assert res.loss < 1e-3 * loss_of(quadratic(), good[0])
    assert all(math.isfinite(p.loss) and math.isfinite(p.best_loss) for p in res.history)
    alone = optimize(nan_for_negative_first_coordinate, good, optimizer=optimizer, iterations=60,
                     lr=LR.get(optimizer))
    assert res.loss == alone.loss
    assert torch.equal(res.x, alone.x)


def misleading_cone(x, mode=None):
    """|x| with a gradient pointing uphill: no line search can find a decrease."""
    value = x.abs().sum(-1) + 1.0
    return value, -torch.sign(x)


@pytest.mark.parametrize("optimizer", ["lbfgs", "bfgs"])
def test_a_point_where_line_searches_keep_failing_is_a_stall(optimizer):
    """Two failed line searches in a row (the second from steepest descent) mark the
    candidate stalled at once: with epsilon = 1 it restarts after the second failed
    search (iteration 2; iteration 0 improves on nothing yet), not only after
    ``patience`` iterations of wasted line searches."""
    x0 = torch.tensor([[0.5, -0.3]], **F64)
    res = optimize(misleading_cone, x0, optimizer=optimizer, iterations=4, epsilon=1.0, patience=50,
                   sample=sample_box(-1.0, 1.0), seed=0)
    flags = [p.restarted for p in res.history]
    assert flags[:3] == [False, False, True]
    no_restart = optimize(misleading_cone, x0, optimizer=optimizer, iterations=4, patience=50,
                          sample=sample_box(-1.0, 1.0), seed=0)
    assert torch.equal(no_restart.x, x0[0])  # without restarts it never leaves


# ------------------------------------------------------------------ multi-start
@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_each_candidate_of_a_batch_follows_its_own_path(optimizer):
    """K guesses as one batch: without restarts every candidate ends exactly where it
    ends alone, for every optimiser. For L-BFGS and BFGS that needs an optimiser per
    candidate (a shared one would give the batch one step length from one line search
    on the summed losses); their evaluations still go out as one batch per call."""
    x0 = torch.tensor([[-1.2, 1.0], [0.0, 0.5], [1.5, 2.5]], **F64)
    lr = 1e-3 if optimizer == "gd" else None
    batched = []

    def counted(x, mode):
        batched.append(x.shape[0])
        return rosenbrock(x, mode)

    res = optimize(counted, x0, optimizer=optimizer, iterations=20, lr=lr)
    assert set(batched) == {3}
    assert res.history[-1].evaluations >= len(batched)  # counted per closure call, cache hits too
    for i in range(3):
        alone = optimize(rosenbrock, x0[i:i + 1], optimizer=optimizer, iterations=20, lr=lr)
        assert torch.equal(res.candidate_x[i], alone.x), i
        assert res.candidate_loss[i].item() == alone.loss, i
    assert res.loss == res.candidate_loss.min().item()
    assert torch.equal(res.x, res.candidate_x[res.best_index])


def cone_left_rosenbrock_right(x, mode=None):
    """Rows with x_0 >= 5 see ``misleading_cone`` around (10, 0) (line searches always
    fail there), the others ``rosenbrock``: two candidates, two different worlds."""
    cone_v, cone_g = misleading_cone(x - torch.tensor([10.0, 0.0], **F64))
    ros_v, ros_g = rosenbrock(x)
    left = x[:, 0] >= 5.0
    return torch.where(left, cone_v, ros_v), torch.where(left[:, None], cone_g, ros_g)


@pytest.mark.parametrize("optimizer", ["lbfgs", "bfgs"])
def test_a_restart_resets_only_the_restarted_candidates_optimizer(optimizer):
    """Candidate 1 keeps failing its line searches and restarts (into the cone region
    again) again and again; candidate 0 improves every iteration on Rosenbrock and keeps
    its own curvature history through its neighbour's restarts, so it ends exactly where
    it ends alone."""

    def into_the_cone(n, gen):
        return torch.tensor([10.0, 0.0], **F64) + (torch.rand(n, 2, generator=gen, **F64) - 0.5)

    x0 = torch.tensor([[-1.2, 1.0], [10.5, -0.3]], **F64)
    res = optimize(cone_left_rosenbrock_right, x0, optimizer=optimizer, iterations=12,
                   epsilon=1.0, patience=50, sample=into_the_cone, seed=0)
    assert sum(p.restarted for p in res.history) >= 2
    alone = optimize(rosenbrock, x0[:1], optimizer=optimizer, iterations=12)
    assert torch.equal(res.candidate_x[0], alone.x)
    assert res.candidate_loss[0].item() == alone.loss


def test_an_error_in_a_batched_evaluation_ends_the_run_with_that_error():
    """An exception from the evaluation (say a simulation error) surfaces from
    ``optimize`` as itself, for candidates with optimisers of their own too, and leaves
    no optimiser thread waiting behind."""
    import threading

    calls = []

    def breaks_on_the_third_call(x, mode):
        calls.append(1)
        if len(calls) == 3:
            raise ValueError("rollout blew up")
        return rosenbrock(x, mode)

    x0 = torch.tensor([[-1.2, 1.0], [0.0, 0.5]], **F64)
    with pytest.raises(ValueError, match="rollout blew up"):
        optimize(breaks_on_the_third_call, x0, optimizer="lbfgs", iterations=10)
    assert not [t for t in threading.enumerate() if t.name.startswith("dejaview-lbfgs")]
