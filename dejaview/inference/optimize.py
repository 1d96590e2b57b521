"""One optimisation loop for every optimiser, gradient mode and restart strategy.

Optimisers are resolved from strings in one place (``make_optimizer``):

- ``gd``: ``torch.optim.SGD`` (plain gradient descent);
- ``adam``: ``torch.optim.Adam``;
- ``lbfgs``: ``torch.optim.LBFGS`` with a strong-Wolfe line search, history 10;
- ``bfgs``: the same L-BFGS with a history at least the parameter count (with
  that much memory it is BFGS whose inverse Hessian is rebuilt from the
  stored pairs: full-rank, as in the original work's BFGS).

Gradients come from the problem in forward or reverse mode; the optimiser
sees them through ``param.grad`` set in its closure. Each ``step`` is one
iteration (L-BFGS runs ``max_iter=1`` per step; its line search may call the
closure more than once). The best loss is tracked over every evaluation,
including line-search trials, and reported from inside the closure (LBFGS's
``step`` returns the loss of its first evaluation only).

Exploration (epsilon-greedy restarts): when the best loss of a candidate has
not improved for ``patience`` iterations, with probability
``epsilon_t = epsilon * (1 - t / iterations)`` (decaying to zero) the
candidate restarts from a fresh random guess inside the start area and the
velocity bounds (explore); otherwise it hops (exploit): it restarts from its
own best point so far plus Gaussian noise in the scaled parameters, with a
standard deviation drawn log-uniformly from ``LocalParams.hop_scale`` (basin hopping: a
stalled local search cannot leave its basin, a hop of the right size lands in
a neighbouring one). Either way the optimiser state is reset, the iteration
is flagged ``restarted`` and the global best is kept. ``epsilon = 0`` switches
exploration off: a stalled candidate carries on.
"Improved" means the candidate's best objective fell by more than
``LocalParams.stall_ratio`` (relative) in that iteration: an L-BFGS run creeping along the
floor of a wrong basin (a small relative gain every iteration) counts as
stalled, not as progress. So does an L-BFGS/BFGS batch whose line search
failed twice in a row (spent its whole budget without improving), which
otherwise costs a full line search per iteration.

Multi-start: ``x0`` may hold K guesses (K, P); they run as one batch, and
each candidate follows the path it would follow alone (with restarts off).
GD and Adam update elementwise, so one optimiser on the summed losses does
that. L-BFGS/BFGS get one ``torch.optim.LBFGS`` per candidate (its own
curvature history, line search and reset), each stepping in a thread of its
own whose closure only hands its trial point over (``_step_each``): the loop
evaluates the trial points of all candidates as one batch once every
candidate is waiting for a value or has finished its step, and a candidate
that finished early is evaluated at its current point (the batch keeps its
shape, so a compiled rollout is not recompiled). One batched call counts as
one evaluation. (A shared L-BFGS on the summed losses would give every
candidate one step length and reset all histories when one candidate
restarts.)
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from dejaview.errors import InferenceError
from dejaview.inference.params import LOCAL_OPTIMIZERS, LocalParams

OPTIMIZERS = LOCAL_OPTIMIZERS
"""The local optimisers this loop runs (``auto`` is the search of ``dejaview.inference.search``)."""


def make_optimizer(name: str, params: list[torch.Tensor], num_params: int, lr: float | None = None,
                   line_search_evals: int = LocalParams.line_search_evals):
    """The torch.optim optimiser called ``name`` (see module docstring); ``lr`` None: its default
    (``LocalParams.step_size``)."""
    if name not in LOCAL_OPTIMIZERS:
        raise InferenceError(f"unknown optimizer {name!r}; choose one of {', '.join(OPTIMIZERS)}")
    lr = LocalParams(optimizer=name).step_size if lr is None else lr
    if name == "gd":
        return torch.optim.SGD(params, lr=lr)
    if name == "adam":
        return torch.optim.Adam(params, lr=lr)
    if name in ("lbfgs", "bfgs"):
        history = 10 if name == "lbfgs" else max(10, num_params)
        # max_eval bounds the line search too (max_ls = max_eval - 1): torch's default for
        # max_iter=1 is 1, which leaves no line search at all (a rejected first trial step = no move).
        # No gradient/change tolerances: torch's absolute 1e-7 / 1e-9 stop a squared-metres objective
        # (|g|^2 ~ 1e-9 at a 1 cm loss) for good; this loop stops by iterations and ``tolerance``
        return torch.optim.LBFGS(params, lr=lr, max_iter=1, max_eval=1 + line_search_evals,
                                 tolerance_grad=0.0, tolerance_change=0.0,
                                 history_size=history, line_search_fn="strong_wolfe")
    raise InferenceError(f"unknown optimizer {name!r}; choose one of {', '.join(OPTIMIZERS)}")


@dataclass
class Progress:
    """What the progress callback receives after every iteration.

    ``phase`` names the stage of a solve: ``search`` (screening, CMA-ES, a local optimiser),
    ``refine`` (Levenberg-Marquardt) or ``sample`` (the posterior sampler); ``fraction`` is how far
    the sampler is (0 to 1; None in the other phases)."""

    iteration: int
    loss: float
    best_loss: float
    duration_s: float
    elapsed_s: float
    restarted: bool
    evaluations: int
    phase: str = "search"
    fraction: float | None = None


@dataclass
class OptimizationResult:
    """Outcome of ``optimize``.

    Attributes:
        x: (P,) best parameters found.
        loss: best loss.
        history: one ``Progress`` per iteration.
        best_index: which candidate of the batch found it.
        stopped: True when ``should_stop`` ended the run early (not set by ``tolerance``).
        candidate_x: (K, P) best parameters each candidate of the batch reached (over the
            whole run, restarts included).
        candidate_loss: (K,) their losses (reported units; inf where never finite).
    """

    x: torch.Tensor
    loss: float
    history: list[Progress] = field(default_factory=list)
    best_index: int = 0
    stopped: bool = False
    candidate_x: torch.Tensor | None = None
    candidate_loss: torch.Tensor | None = None


def optimize(value_and_grad: Callable[[torch.Tensor, str], tuple[torch.Tensor, torch.Tensor]],
             x0: torch.Tensor, *, optimizer: str = "lbfgs", iterations: int = 200,
             gradient: str = "forward", lr: float | None = None, epsilon: float = 0.0,
             patience: int = 25, sample: Callable[[int, torch.Generator], torch.Tensor] | None = None,
             seed: int = 0, callback: Callable[[Progress], None] | None = None,
             should_stop: Callable[[], bool] | None = None,
             tolerance: float | None = None,
             report: Callable[[float], float] | None = None,
             constants: LocalParams | None = None) -> OptimizationResult:
    """Minimise a batched loss.

    Each iteration is a fixed sequence of named steps of ``_LocalRun``: the optimiser step, the
    reset of failed line searches, the replacement of non-finite points, the stall
    bookkeeping, the epsilon-greedy restarts and the progress report.

    Args:
        value_and_grad: (x (K, P), mode) -> (losses (K,), gradients (K, P)).
        x0: (K, P) initial guesses (K >= 1 candidates run as one batch).
        optimizer: ``gd`` | ``adam`` | ``lbfgs`` | ``bfgs``.
        iterations: number of iterations (>= 1).
        gradient: ``forward`` | ``reverse``.
        lr: learning rate (default per optimiser).
        epsilon, patience: epsilon-greedy restarts (epsilon 0: none).
        sample: (n, generator) -> (n, P) fresh guesses, needed for restarts.
        seed: seeds the restart draws.
        callback: called with a ``Progress`` after every iteration.
        should_stop: polled every iteration; True stops the run (cancellation).
        tolerance: stop once the best reported loss is at or below this (None: run all iterations).
        constants: ``LocalParams`` whose ``stall_ratio``, ``line_search_evals`` and ``hop_scale``
            the loop runs with (None: the defaults).
        report: maps objective values to the losses reported in ``Progress`` and the
            result (e.g. ``sqrt(2 v)`` for a squared objective; default: identity).
    Returns:
        OptimizationResult with the best parameters over the whole run.
    """
    _check_settings(optimizer, gradient, iterations, epsilon, sample)
    run = _LocalRun(value_and_grad, x0, optimizer=optimizer, gradient=gradient, lr=lr, patience=patience,
                    sample=sample, seed=seed, report=report, constants=constants or LocalParams())
    stopped = False
    for it in range(int(iterations)):
        if should_stop is not None and should_stop():
            stopped = True
            break
        t0 = time.perf_counter()
        before, x_before = run.cand_best.clone(), run.points().clone()
        calls = run.step()
        run.reset_failed_line_searches(x_before)
        run.replace_non_finite()
        run.update_stalls(before, calls)
        restarted = epsilon > 0 and run.restart_stalled(epsilon * (1.0 - it / iterations))
        run.share_points()
        prog = run.report(it, t0, restarted)
        if callback is not None:
            callback(prog)
        if tolerance is not None and prog.best_loss <= tolerance:
            break
    return run.result(stopped)


def _check_settings(optimizer: str, gradient: str, iterations: int, epsilon: float,
                    sample: Callable | None) -> None:
    """Raise ``InferenceError`` naming the first setting of ``optimize`` that is out of range."""
    if optimizer not in OPTIMIZERS:
        raise InferenceError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    if gradient not in ("forward", "reverse"):
        raise InferenceError(f"unknown gradient mode {gradient!r}; choose forward or reverse")
    if isinstance(iterations, bool) or int(iterations) != iterations or iterations < 1:
        raise InferenceError(f"iterations must be a positive integer, got {iterations!r}")
    if epsilon > 0 and sample is None:
        raise InferenceError("restarts (epsilon > 0) need a way to sample fresh guesses")


class _LocalRun:
    """The state of one ``optimize`` run and the steps of its iterations.

    Attributes:
        x: (K, P) parameter of the whole batch (the one optimiser's parameter unless ``each``).
        each: one L-BFGS per candidate (``xs[i]`` (1, P) their parameters) instead of one optimiser.
        opts: the optimisers (one, or K with ``each``).
        best_x, best_loss, best_index: best point over every evaluation (objective units).
        cand_best: (K,) each candidate's best objective since its last restart.
        since_improved: (K,) iterations since each candidate last improved (``LocalParams.stall_ratio``).
        failed_before: (K,) whether each candidate's line search failed in the previous iteration.
        keep_x, keep_loss: (K, P), (K,) each candidate's best point over the whole run (never reset).
        evaluations: batched evaluations so far.
        last: (K,) safe losses of the latest evaluation (None before the first).
        history: one ``Progress`` per iteration.
    """

    def __init__(self, value_and_grad, x0: torch.Tensor, *, optimizer: str, gradient: str,
                 lr: float | None, patience: int, sample, seed: int, report, constants: LocalParams) -> None:
        self.c = constants  # stall_ratio, line_search_evals, hop_scale
        self.value_and_grad = value_and_grad
        self.optimizer = optimizer
        self.gradient = gradient
        self.lr = lr
        self.patience = patience
        self.sample = sample
        self.shown = report or (lambda v: v)
        self.gen = torch.Generator().manual_seed(int(seed))
        self.x = x = torch.nn.Parameter(x0.detach().clone())
        self.k, self.p = k, p = x.shape
        # one L-BFGS per candidate of a batch (see the module docstring); one optimiser otherwise
        self.each = optimizer in ("lbfgs", "bfgs") and k > 1
        self.xs = ([torch.nn.Parameter(x.detach()[i:i + 1].clone()) for i in range(k)]
                   if self.each else [x])
        self.opts = [make_optimizer(optimizer, [xi], p, lr, self.c.line_search_evals) for xi in self.xs]
        self.best_x = x.detach()[0].clone()
        self.best_loss = math.inf
        self.best_index = 0
        self.cand_best = torch.full((k,), math.inf, dtype=x.dtype)
        self.since_improved = torch.zeros(k, dtype=torch.long)
        self.failed_before = torch.zeros(k, dtype=torch.bool)
        self.keep_loss = torch.full((k,), math.inf, dtype=x.dtype)
        self.keep_x = x.detach().clone()
        self.history: list[Progress] = []
        self.start = time.perf_counter()
        self.evaluations = 0
        self.last: torch.Tensor | None = None
        self._cache: dict = {}

    def points(self) -> torch.Tensor:
        """(K, P) the candidates' current points."""
        return torch.cat([xi.detach() for xi in self.xs]) if self.each else self.x.detach()

    def _evaluate(self, xv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # L-BFGS re-evaluates the point its line search ended on: reuse that result
        if "x" in self._cache and torch.equal(self._cache["x"], xv):
            return self._cache["value"]
        value = self.value_and_grad(xv, self.gradient)
        self._cache.update(x=xv.clone(), value=value)
        return value

    def record(self, xv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Evaluate the batch xv (K, P) and book it: -> (safe losses (K,), gradients (K, P))."""
        losses, grad = self._evaluate(xv)
        self.evaluations += 1
        finite = torch.isfinite(losses) & torch.isfinite(grad).all(-1)
        # a NaN candidate must not poison the optimiser: zero its gradient, count it as +inf
        grad = torch.where(finite[:, None], grad, torch.zeros_like(grad)).to(self.x.dtype)
        safe = torch.where(finite, losses, torch.full_like(losses, 1e6))
        i = int(torch.argmin(safe))
        if finite[i] and safe[i].item() < self.best_loss:
            self.best_loss = safe[i].item()
            self.best_x = xv[i].clone()
            self.best_index = i
        improved = safe < self.cand_best
        self.cand_best.copy_(torch.where(improved, safe, self.cand_best))
        kept = finite & (safe < self.keep_loss)
        self.keep_loss.copy_(torch.where(kept, safe, self.keep_loss))
        self.keep_x.copy_(torch.where(kept[:, None], xv, self.keep_x))
        self.last = safe
        return safe, grad

    def _closure(self) -> torch.Tensor:
        safe, grad = self.record(self.x.detach())
        self.x.grad = grad
        return safe.sum()

    def step(self) -> torch.Tensor:
        """One step of the optimiser(s) -> (K,) long: closure calls per candidate."""
        if self.each:
            calls = _step_each(self.opts, self.xs, self.record)
            with torch.no_grad():
                self.x.copy_(self.points())
            return calls
        evals_before = self.evaluations
        self.opts[0].step(self._closure)
        return torch.full((self.k,), self.evaluations - evals_before)

    def reset_failed_line_searches(self, x_before: torch.Tensor) -> None:
        """Fresh L-BFGS/BFGS for the candidates that did not move from ``x_before`` (K, P)."""
        if self.optimizer not in ("lbfgs", "bfgs"):
            return
        # a failed line search leaves x where it was and would fail the same way again:
        # drop the curvature history so the next step starts from steepest descent
        for i in range(len(self.opts)):
            if torch.equal(self.xs[i].detach(), x_before[i:i + 1] if self.each else x_before):
                self.opts[i] = make_optimizer(self.optimizer, [self.xs[i]], self.p, self.lr, self.c.line_search_evals)

    def replace_non_finite(self) -> None:
        """Restart the candidates whose parameters are not finite from a fresh draw."""
        with torch.no_grad():
            # keep parameters finite (a diverging GD step): restart those from a fresh draw
            bad = ~torch.isfinite(self.x).all(-1)
            if bad.any() and self.sample is not None:
                self.x[bad] = self.sample(int(bad.sum()), self.gen).to(self.x.dtype)

    def update_stalls(self, before: torch.Tensor, calls: torch.Tensor) -> None:
        """Count iterations without improvement; ``before``: (K,) ``cand_best`` before the step."""
        improved = self.cand_best < before * (1.0 - self.c.stall_ratio)
        since = torch.where(improved, torch.zeros_like(self.since_improved), self.since_improved + 1)
        # a line search that spent its whole budget without improving anything failed (torch's
        # strong Wolfe search may still nudge x by a hair, so "x did not move" misses most);
        # a shared one fails for all candidates, one of a candidate's own for that candidate
        failed = ((calls >= self.c.line_search_evals) & ~(improved if self.each else improved.any())
                  if self.optimizer in ("lbfgs", "bfgs") else torch.zeros(self.k, dtype=torch.bool))
        # two in a row: a kink of the loss (a contact that starts or ends) where more line
        # searches only burn evaluations; the candidate is stalled now
        self.since_improved = torch.where(failed & self.failed_before,
                                          since.clamp(min=self.patience), since)
        self.failed_before = failed

    def restart_stalled(self, eps_t: float) -> bool:
        """Restart or hop the stalled candidates (epsilon-greedy with ``eps_t``) -> any restarted."""
        k, p, dtype, gen = self.k, self.p, self.x.dtype, self.gen
        stale = self.since_improved >= self.patience
        fresh = stale & (torch.rand(k, generator=gen) < eps_t)
        if not stale.any():
            return False
        lo, hi = (math.log(v) for v in self.c.hop_scale)
        sigma = torch.exp(lo + (hi - lo) * torch.rand(k, 1, generator=gen, dtype=dtype))
        hop = self.keep_x + sigma * torch.randn(k, p, generator=gen, dtype=dtype)
        with torch.no_grad():
            self.x.copy_(torch.where((stale & ~fresh)[:, None], hop, self.x))
            if fresh.any():
                self.x[fresh] = self.sample(int(fresh.sum()), gen).to(dtype)
        self.since_improved = torch.where(stale, torch.zeros_like(self.since_improved),
                                          self.since_improved)
        self.cand_best = torch.where(stale, torch.full_like(self.cand_best, math.inf), self.cand_best)
        # a restarted candidate starts a fresh optimiser (the shared one: all of them)
        for i in range(len(self.opts)):
            if not self.each or stale[i]:
                self.opts[i] = make_optimizer(self.optimizer, [self.xs[i]], p, self.lr, self.c.line_search_evals)
        return True

    def share_points(self) -> None:
        """Copy the batch parameter's rows (replaced or restarted ones) into each candidate's own."""
        if self.each:
            with torch.no_grad():
                for i in range(self.k):
                    self.xs[i].copy_(self.x[i:i + 1])

    def report(self, it: int, t0: float, restarted: bool) -> Progress:
        """Book and return the ``Progress`` of iteration ``it`` (begun at ``t0``)."""
        current = float(self.last.min()) if self.last is not None else math.nan
        prog = Progress(iteration=it, loss=self.shown(current), best_loss=self.shown(self.best_loss),
                        duration_s=time.perf_counter() - t0, elapsed_s=time.perf_counter() - self.start,
                        restarted=restarted, evaluations=self.evaluations)
        self.history.append(prog)
        return prog

    def result(self, stopped: bool) -> OptimizationResult:
        """The ``OptimizationResult`` of the run so far."""
        shown = self.shown
        return OptimizationResult(x=self.best_x, loss=shown(self.best_loss), history=self.history,
                                  best_index=self.best_index, stopped=stopped, candidate_x=self.keep_x,
                                  candidate_loss=torch.tensor([shown(float(v)) for v in self.keep_loss],
                                                              dtype=self.keep_loss.dtype))


def _step_each(opts: list, xs: list[torch.Tensor],
               evaluate: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """One ``step`` of every optimiser in ``opts``, their evaluations batched.

    ``opts[i]`` optimises ``xs[i]`` (1, P) alone. Each steps in a thread of its own whose
    closure publishes that it wants a value and waits; once every optimiser is waiting or
    has finished its step, this (calling) thread evaluates all K points at once, the ones
    of finished optimisers included, and hands each waiting closure its row.

    Args:
        opts: K optimisers (``torch.optim.LBFGS``), one per candidate.
        xs: K parameters (1, P), each the only parameter of its optimiser.
        evaluate: (K, P) points -> (losses (K,), gradients (K, P)).
    Returns:
        (K,) long: how many times each optimiser's closure was called.
    """
    k = len(opts)
    cond = threading.Condition()
    waiting: set[int] = set()
    finished: set[int] = set()
    answers: dict[int, tuple[torch.Tensor, torch.Tensor] | None] = {}
    errors: list[BaseException] = []
    calls = torch.zeros(k, dtype=torch.long)

    def run(i: int) -> None:
        def closure():
            with cond:
                calls[i] += 1
                waiting.add(i)
                cond.notify_all()
                while i not in answers:
                    cond.wait()
                answer = answers.pop(i)
            if answer is None:
                raise _Aborted()
            loss, grad = answer
            xs[i].grad = grad
            return loss

        try:
            opts[i].step(closure)
        except _Aborted:
            pass
        except BaseException as exc:  # re-raised in the calling thread
            errors.append(exc)
        finally:
            with cond:
                finished.add(i)
                cond.notify_all()

    threads = [threading.Thread(target=run, args=(i,), name=f"dejaview-lbfgs-{i}", daemon=True)
               for i in range(k)]
    for t in threads:
        t.start()
    try:
        with cond:
            while True:
                while len(waiting) + len(finished) < k:
                    cond.wait()
                if not waiting or errors:
                    break
                with torch.enable_grad():
                    losses, grads = evaluate(torch.cat([xi.detach() for xi in xs]))
                for i in waiting:
                    answers[i] = (losses[i], grads[i:i + 1])
                waiting.clear()
                cond.notify_all()
    finally:
        with cond:  # release every closure still waiting (an error here or in a thread)
            for i in range(k):
                if i not in finished:
                    answers[i] = None
            cond.notify_all()
        for t in threads:
            t.join()
    if errors:
        raise errors[0]
    return calls


class _Aborted(Exception):
    """Raised in an optimiser's closure to end its step when the batch evaluation failed."""
