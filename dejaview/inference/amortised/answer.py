"""Answering from an amortised posterior: weighed by the exact likelihood, or live from the flow.

``answer(post, model, samples)`` (``dejaview solve --amortised MODEL``):

1. draw ``max(min_draws, draws * samples)`` starts from the flow q(x | y) at the scene's
   observation vector y (``observables.observed``);
2. simulate each once for its exact posterior density p(x | y) (``reference.log_density``: the
   likelihood, the prior, 0 where the start interpenetrates) and weigh it by p / q, Pareto-smoothed
   (``psis``): the weighted draws are exact in the limit of many draws, whatever the flow's
   errors, so long as q covers p; k-hat says whether it does;
3. the most probable start: the ``refine`` best distinct draws refined by Levenberg-Marquardt on
   the exact Jacobian (the default search's last stage, ``search._Search.refine``);
4. where k-hat is at most ``max_k_hat`` the samples are the weighted draws, resampled (two
   halves of the draws as two independent runs, so ``result.json``'s R-hat compares two
   importance-sampling estimates); above it the flow does not fit this observation and the
   samples come from the sampler (``Sampler``) started at the refined modes with the flow in its
   proposal mixture (``flow_share``): the answer says so (``amortised.fitted`` false).

``live(post, model)`` answers without a rollout: ``live_draws`` from the flow, their start
positions' histogram over the start area, the flow's most probable draw and whether the
observation lies among the training observations (``AmortisedModel.like_training``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from dejaview.inference.params import AmortisedParams, SamplerParams, SearchParams


@dataclass
class FlowProposal:
    """The flow at one observation as a proposal of the sampler's reference mixture
    (``reference.Mixture.flow``): ``sample(n, gen)`` -> x (n, P), ``log_prob(x)`` -> (B,)."""

    model: object
    post: object
    y: torch.Tensor

    def sample(self, n: int, gen: torch.Generator) -> torch.Tensor:
        return self.model.sample(self.post, self.y, n, gen)[0]

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        out = self.model.log_prob(self.post, self.y, x)
        return torch.where(torch.isfinite(out), out, torch.full_like(out, -math.inf))


def _resample(log_w: torch.Tensor, k: int, gen: torch.Generator) -> torch.Tensor:
    """k indices (k,) drawn systematically by normalised log weights log_w (S,)."""
    w = torch.softmax(torch.where(torch.isfinite(log_w), log_w, torch.full_like(log_w, -math.inf)), 0)
    u = (torch.rand(1, generator=gen, dtype=w.dtype) + torch.arange(k, dtype=w.dtype)) / k
    return torch.searchsorted(torch.cumsum(w, 0), u).clamp_max(log_w.shape[0] - 1)


def answer(post, model, samples: int, *, params: AmortisedParams | None = None, seed: int = 0,
           search: SearchParams | None = None, callback=None, should_stop=None):
    """The answer to ``post``'s observation from ``model`` (module docstring).

    Args:
        post: the scene's ``Posterior``; model: an ``AmortisedModel`` trained for it (checked).
        samples: posterior samples wanted (0: the most probable start alone).
        params: ``AmortisedParams``; seed: seeds the draws; search: ``SearchParams`` of the refinement.
    Returns:
        (``SearchResult`` of the refinement, ``PosteriorSamples`` or None, the report dict for
        ``result.json``'s ``amortised``).
    """
    from dejaview.inference.amortised.observables import observed
    from dejaview.inference.amortised.psis import psis
    from dejaview.inference.reference import log_density
    from dejaview.inference.sampling import PosteriorSamples, Sampler
    from dejaview.inference.search import MapSearch, SearchResult, _Search

    p = AmortisedParams() if params is None else params
    search = SearchParams(seed=seed) if search is None else search
    model.check_fits(post)
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(int(seed) * 9973 + 5)
    y = observed(post)
    n_draw = max(p.min_draws, p.draws * samples)
    if n_draw % 2:
        n_draw += 1
    x, log_q = model.sample(post, y, n_draw, gen)
    rollouts0 = post.rollouts
    lp = log_density(post, x)
    log_w = torch.where(torch.isfinite(lp) & torch.isfinite(log_q), lp - log_q, torch.full_like(lp, -math.inf))
    smoothed, k_hat = psis(log_w)
    w = torch.softmax(smoothed, 0)
    ess = float(1.0 / (w * w).sum()) if bool(torch.isfinite(smoothed).any()) else 0.0
    fitted = math.isfinite(k_hat) and k_hat <= p.max_k_hat
    report = {"model": model.info.get("scene"), "draws": n_draw, "k_hat": k_hat, "max_k_hat": p.max_k_hat,
              "ess": ess, "fitted": fitted, "feasible_share": float(torch.isfinite(lp).double().mean()),
              "like_training": model.like_training(y)}
    if callback is not None:
        callback({"phase": "weigh", "fraction": 0.5, "elapsed_s": time.perf_counter() - t0})
    # the most probable start: the best distinct draws, refined (where the flow fits), or seeding
    # the default search (where it does not: its draws are then no better than the prior's)
    order = torch.argsort(torch.where(torch.isfinite(lp), -lp, torch.full_like(lp, math.inf)))
    picks = []
    for i in order.tolist():
        if not math.isfinite(float(lp[i])) or len(picks) >= p.refine:
            break
        if all(float((x[i] - x[j]).norm()) >= search.seed_spacing for j in picks):
            picks.append(i)
    if not picks:
        from dejaview.errors import InferenceError

        raise InferenceError(f"none of the amortised model's {n_draw} draws is a possible start for this "
                             f"observation (each interpenetrates an object or its rollout is not finite)")
    if fitted:
        runner = _Search(post, search, None, should_stop)
        runner.add_modes(runner.refine(x[picks], search.lm_final_iterations))
        if not runner.modes:
            from dejaview.errors import InferenceError

            raise InferenceError("the refinement of the amortised model's best draws lost every one of them")
        modes = runner.modes
        best = modes[0]
        opt = SearchResult(x=best.x, loss=best.loss, history=runner.history, best_index=0, stopped=runner.stopped,
                           candidate_x=torch.stack([m.x for m in modes]),
                           candidate_loss=torch.tensor([m.loss for m in modes], dtype=torch.float64),
                           cost=best.cost, chi2=best.chi2, modes=modes, rollouts=post.rollouts - rollouts0,
                           jacobians=post.jacobians)
    else:
        opt = MapSearch(search).run(post, should_stop=should_stop, seeds=x[picks])
        opt.rollouts = post.rollouts - rollouts0
        modes = opt.modes
        report["search"] = "the default search, seeded with the model's best draws"
    drawn = None
    if samples and fitted:
        half = n_draw // 2
        keep = [samples // 2 + samples % 2, samples // 2]
        rows, runs = [], []
        for r, (a, b) in enumerate(((0, half), (half, n_draw))):
            if keep[r]:
                sm, _ = psis(log_w[a:b])
                rows.append(a + _resample(sm, keep[r], gen))
                runs.append(torch.full((keep[r],), r, dtype=torch.long))
        idx = torch.cat(rows)
        means = torch.stack([m.x for m in modes])
        drawn = PosteriorSamples(x=x[idx].clone(), weights=torch.full((samples,), 1.0 / samples, dtype=torch.float64),
                                 log_density=lp[idx].clone(), component=torch.cdist(x[idx], means).argmin(-1),
                                 mode_index=list(range(len(modes))), run=torch.cat(runs),
                                 stats={"method": "amortised", "draws": n_draw, "k_hat": k_hat, "ess": ess,
                                        "unique_samples": int(torch.unique(idx).numel()),
                                        "rollouts": post.rollouts - rollouts0,
                                        "seconds": time.perf_counter() - t0})
    elif samples:
        drawn = Sampler(SamplerParams(seed=seed)).sample(post, modes, samples, callback=callback,
                                                         should_stop=should_stop, proposal=FlowProposal(model, post, y),
                                                         proposal_share=p.flow_share)
        report["fallback"] = "sampler"
    report["seconds"] = time.perf_counter() - t0
    return opt, drawn, report


def live(post, model, *, params: AmortisedParams | None = None, cells: tuple[int, int] = (16, 16), seed: int = 0,
         y: torch.Tensor | None = None) -> dict:
    """A live answer from the flow alone (module docstring): no rollout.

    Args:
        post: the scene's ``Posterior`` (its observation, unless ``y`` (D,) is given).
        cells: the heatmap's (nx, ny) over the start area.
    Returns:
        dict: ``samples`` (n, 3) start positions, ``heatmap`` {min, max, cells, probability} as
        ``heatmap.json``, ``most_probable`` (the draw the flow finds likeliest) as an
        ``initial_state``, ``fitted`` (the observation lies among the training observations),
        ``seconds``.
    """
    from dejaview.inference.amortised.observables import observed
    from dejaview.inference.posterior_report import position_histogram

    p = AmortisedParams() if params is None else params
    t0 = time.perf_counter()
    y = observed(post) if y is None else y
    gen = torch.Generator().manual_seed(int(seed))
    x, best = model.draw(post, y, p.live_draws, gen)
    lay = post.layout
    with torch.no_grad():
        dec = lay.decode(x)
    out = {"samples": dec["position"], "fitted": model.like_training(y)}
    out["most_probable"] = {k: v[int(best)].tolist() for k, v in dec.items()}
    if lay.lo is not None:
        lo, hi = lay.lo.reshape(-1)[:2].tolist(), lay.hi.reshape(-1)[:2].tolist()
        w = torch.full((x.shape[0],), 1.0 / x.shape[0], dtype=torch.float64)
        prob = position_histogram(dec["position"], w, tuple(lo), tuple(hi), cells)
        out["heatmap"] = {"min": lo, "max": hi, "cells": list(cells), "probability": prob.tolist()}
    out["seconds"] = time.perf_counter() - t0
    return out


__all__ = ["FlowProposal", "answer", "live"]
