"""The seed's local pipeline: screened guesses, a local optimiser and epsilon-greedy restarts.

``fit_locally(problem, LocalParams(optimizer="lbfgs"))`` is what a scene with
``optimizer="gd|adam|lbfgs|bfgs"`` runs (``dejaview.inference.solve``): the guesses
are screened by their loss without gradients (``screen_rounds_ranked``), the best
ones start the optimiser (``dejaview.inference.optimize``), which hops away from a
stalled start with probability ``epsilon`` (restarts from the next screened guesses).
The default search (``optimizer="auto"``) is ``dejaview.inference.search.MapSearch``.
"""

from __future__ import annotations

import math
import torch

from dejaview.errors import InferenceError
from dejaview.inference.optimize import OPTIMIZERS, optimize
from dejaview.inference.params import LocalParams
from dejaview.backends.base import objective_to_loss


def _check_count(value, what: str, minimum: int) -> None:
    """One-line error unless ``value`` is an int (not a bool) of at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        kind = "positive" if minimum == 1 else "non-negative"
        raise InferenceError(f"{what} must be a {kind} integer, got {value!r}")


def default_gradient(num_params: int) -> str:
    """The faster gradient mode for a problem (scene format: ``gradient`` defaults to it).

    In principle forward mode wins for the ~12 parameters of one object (no
    graph to store, P tangents in one batched pass). On the torch engine, eager
    forward-mode AD pays Python decompositions for every op with a constant
    operand (a World tensor, a Python number: its zero tangent is sized through
    ``torch._refs``), so reverse mode is faster there, and on the native engine
    the adjoint reverse pass is (numbers: ``docs/benchmarks.md``, "Forward-mode
    cost on the torch engine" and the engine benchmarks). Reverse mode is
    therefore the default for every size; forward mode stays available
    (``gradient="forward"``) and gives the same gradients.
    """
    del num_params
    return "reverse"




def _check_count(value, what: str, minimum: int) -> None:
    """One-line error unless ``value`` is an int (not a bool) of at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        kind = "positive" if minimum == 1 else "non-negative"
        raise InferenceError(f"{what} must be a {kind} integer, got {value!r}")


def screen_guesses(problem, first: torch.Tensor, count: int, generator: torch.Generator,
                   should_stop=None, batch: int = LocalParams.screen_batch, rounds: int = 1,
                   elite: int | None = None, near: float = LocalParams.screen_near,
                   sigma: float = LocalParams.screen_sigma) -> tuple[torch.Tensor, torch.Tensor]:
    """Rank initial guesses by their loss, without gradients (a cheap global step).

    The guesses and losses of ``screen_rounds_ranked`` (same arguments), without the round
    each guess came from.
    """
    x, loss, _ = screen_rounds_ranked(problem, first, count, generator, should_stop=should_stop,
                                      batch=batch, rounds=rounds, elite=elite, near=near,
                                      sigma=sigma)
    return x, loss


def screen_rounds_ranked(problem, first: torch.Tensor, count: int, generator: torch.Generator,
                         should_stop=None, batch: int = LocalParams.screen_batch, rounds: int = 1,
                         elite: int | None = None, near: float = LocalParams.screen_near,
                         sigma: float = LocalParams.screen_sigma
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rank initial guesses by their loss, without gradients, and say which round drew each.

    The guesses are ``first`` plus ``count`` random draws: a fraction ``1 - near``
    from the whole prior (``problem.layout.sample``: start area, any orientation,
    velocities in the layout's bounds) and a fraction ``near`` around the scene's
    own guess ``first[0]`` (normal, standard deviation ``sigma`` in the scaled
    parameters). The scene's guess is the user's prior (a mug upright on the
    counter), and the prior alone almost never comes near it: its rotation
    vectors fill the ball of radius pi uniformly, so one lies within 30 degrees
    of the given orientation with probability (1/6)^3 = 0.5 %, and 64 draws hold
    a third of a guess that starts upright; the solver would then only try pasts
    that start tumbling. The guesses are simulated in batches of ``batch``
    without autograd, which costs a fraction of a loss + gradient per candidate
    (docs/benchmarks.md, "Simulator"), so screening a few hundred draws costs a
    handful of gradient evaluations and
    moves the start into the right basin where the scene's guess tells a
    different story.

    ``rounds > 1`` refines the ranking by the cross-entropy method: each further
    round draws ``count`` guesses from a normal distribution (diagonal, in the
    scaled parameters) fitted to the ``elite`` best guesses so far (default
    ``max(4, count // 8)``), so the search narrows onto the most promising basin
    where the loss is flat or kinked and a gradient step would not get far.

    Args:
        problem: a backend problem (``loss(x) -> (K,)``).
        first: (F, P) guesses that always take part (the scene's own).
        count: number of random draws per round.
        generator: seeds the draws.
        should_stop: polled between batches; True ends screening with what was ranked.
        rounds: 1 + the number of cross-entropy refinements.
        elite: guesses the refinements fit their distribution to.
        near: fraction of the first round's draws around ``first[0]`` (0: all from the prior).
        sigma: their standard deviation (scaled parameters).
    Returns:
        guesses (M, P) sorted by loss (best first; non-finite losses last), their losses (M,)
        and the round that drew each (M,) (0: the first round, with ``first``).
    """
    _check_count(rounds, "screen rounds", 1)
    elite = max(4, count // 8) if elite is None else int(elite)
    guesses, losses, drawn_in = [], [], []
    stopped = False
    for r in range(rounds):
        if r == 0:
            n_near = int(round(count * near))
            x = torch.cat([first, problem.layout.sample(count - n_near, generator).to(first.dtype),
                           first[:1] + sigma * torch.randn(n_near, first.shape[1], generator=generator,
                                                           dtype=first.dtype)], 0)
        else:
            loss = torch.cat(losses)
            keep = torch.argsort(loss, stable=True)[:elite]
            best = torch.cat(guesses)[keep[torch.isfinite(loss[keep])]]
            if best.shape[0] < 2:
                break
            mean, std = best.mean(0), best.std(0).clamp_min(1e-3)
            x = mean + std * torch.randn(count, first.shape[1], generator=generator, dtype=first.dtype)
        with torch.no_grad():
            for chunk in x.split(batch):
                if guesses and should_stop is not None and should_stop():
                    stopped = True
                    break
                value = problem.loss(chunk).detach().to(first.dtype)
                guesses.append(chunk)
                drawn_in.append(torch.full((chunk.shape[0],), r, dtype=torch.long))
                losses.append(torch.where(torch.isfinite(value), value, torch.full_like(value, math.inf)))
        if stopped:
            break
    x, loss, drawn = torch.cat(guesses), torch.cat(losses), torch.cat(drawn_in)
    order = torch.argsort(loss, stable=True)
    return x[order], loss[order], drawn[order]


def restart_pool(ranked: torch.Tensor, drawn: torch.Tensor) -> list[torch.Tensor]:
    """The order in which restarts take screened guesses that were not used as starts.

    Restarts explore, so the first round's guesses (drawn over the whole prior) come first,
    best first; the refinement rounds' guesses follow. Those crowd around the best guess,
    i.e. around the start, where the optimiser's own hops (``optimize``) already search.

    Args:
        ranked: (M, P) guesses sorted by loss (``screen_rounds_ranked``).
        drawn: (M,) the round that drew each.
    Returns:
        M guesses (P,), in the order restarts take them.
    """
    return list(ranked[drawn == 0]) + list(ranked[drawn > 0])


def fit_locally(problem, params: LocalParams, x0: torch.Tensor | None = None, *, callback=None,
                should_stop=None):
    """The seed's local pipeline: a local optimiser (``gd|adam|lbfgs|bfgs``) on ``0.5 * loss^2``
    with epsilon-greedy restarts, from the scene's guess, ``x0`` (K, P), or screened guesses.

    Args:
        problem: a backend problem (any backend: ``objective_and_grad``, ``loss``, ``layout``).
        params: ``LocalParams``.
        x0: starts (K, P) (None: the scene's guess, with ``screen`` and ``multistart``).
        callback: called with a ``Progress`` after every iteration; should_stop: polled.
    Returns:
        (``OptimizationResult``, the settings it ran with for ``result.json``).
    Raises:
        InferenceError: a gradient mode the backend does not offer.
    """
    settings = params
    gradient = settings.gradient or default_gradient(problem.num_params)
    if gradient not in problem.gradient_modes:
        raise InferenceError(f"the {problem.backend} backend offers {' and '.join(problem.gradient_modes)}-mode "
                             f"gradients only, not {gradient} mode; use --gradient reverse")
    s = params
    gen = torch.Generator().manual_seed(int(s.seed))
    sample = problem.layout.sample
    screened = 0
    if x0 is None:
        x0 = problem.layout.encode().to(problem.dtype)
        if s.screen > 0:
            ranked, _, drawn = screen_rounds_ranked(problem, x0, max(s.screen, s.multistart - 1), gen,
                                                    should_stop=should_stop, rounds=s.screen_rounds,
                                                    near=s.screen_near)
            screened = ranked.shape[0]
            x0, pool = ranked[:s.multistart], restart_pool(ranked[s.multistart:], drawn[s.multistart:])

            def sample(n, generator):
                """Restarts: the next-best screened guesses, then fresh draws."""
                taken = [pool.pop(0) for _ in range(min(n, len(pool)))]
                parts = [torch.stack(taken)] if taken else []
                if n > len(taken):
                    parts.append(problem.layout.sample(n - len(taken), generator).to(x0.dtype))
                return torch.cat(parts, 0)
        elif s.multistart > 1:
            x0 = torch.cat([x0, problem.layout.sample(s.multistart - 1, gen)], 0)
    x0 = x0.to(problem.dtype)
    opt = optimize(problem.objective_and_grad, x0, optimizer=s.optimizer, iterations=s.iterations,
                   gradient=gradient, lr=s.lr, epsilon=s.epsilon, patience=s.patience, sample=sample,
                   seed=s.seed, callback=callback, should_stop=should_stop, tolerance=s.tolerance,
                   report=objective_to_loss, constants=s)
    return opt, {"gradient": gradient, "multistart": s.multistart, "epsilon": s.epsilon,
                 "patience": s.patience, "screened": screened}
