"""Training an amortised posterior: simulate (start, observation) pairs, fit the flow.

``train(scene, TrainParams(...))``:

1. **Simulate.** Chunks of ``chunk`` starts drawn from the scene's prior (``prior_draws``: the
   start area, ``<prior>``, the physics prior), each chunk from its own generator (``seed``
   and its index), so the training set is the same whether this process, a pool of processes
   or Ray actors simulate it (``dejaview.parallel.map_chunks``). Starts that interpenetrate
   another object are dropped (the posterior gives them no mass); the rest are simulated on the
   scene's own physics and their observation vectors (``observables.simulated``) get the
   observation noise (``observables.noisy``). Rounds of chunks run until ``simulations`` pairs
   are in hand (the share of feasible starts is measured by the first round).
2. **Fit.** The flow (``model.FlowShape``) maximises the likelihood of the starts given their
   observations (neural posterior estimation, Papamakarios and Murray 2016; Greenberg et al.
   2019), in standardised flow coordinates (``coordinates``), Adam with a cosine schedule,
   ``validation`` of the pairs held out to choose the epoch and stop (``patience``,
   ``max_fit_seconds``).

Why zuko and not sbi: sbi's NPE wraps the same kind of flow (it can build zuko's) in a trainer
that owns the simulations, the prior and the training loop, and pickles its posterior; here the
simulations come from the native engine in our own chunks, the prior needs our bounded and
SO(3) coordinates, the training loop is 30 lines, and the model must be a file that runs no code
when loaded. zuko is the flow alone (torch modules, no other dependency).
"""

from __future__ import annotations

import math
import time

import torch

from dejaview.errors import InferenceError
from dejaview.inference.params import TrainParams

NEIGHBOURS = 2000
"""Training observations kept in the model to judge whether a live observation is like them."""


def _setup(scene):
    """A worker's posterior of the scene (``dejaview.parallel`` setup): its own physics, no variants."""
    from dejaview.inference.posterior import Posterior

    return Posterior.from_scene(scene).without_model()


def _chunk(post, item, report, stopped):
    """One chunk: (index, draws, seed, rollout batch) -> (x (M, P), y (M, D), draws, feasible) of its
    feasible, finite simulations, simulated ``rollout batch`` at a time (0: all at once; each
    rollout is independent of its batch, so the pairs are the same)."""
    from dejaview.inference.amortised.observables import noisy, simulated, width
    from dejaview.inference.reference import prior_draws

    index, n, seed, batch = item
    gen = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(index))
    x = prior_draws(post, n, gen)
    ok = post.feasible(x)
    x = x[ok]
    if x.shape[0] == 0 or stopped():
        return x, torch.zeros(0, width(post), dtype=torch.float64), n, 0
    with torch.no_grad():
        y = torch.cat([simulated(post, post.trajectories(part)[0]).to(torch.float64)
                       for part in x.split(batch or x.shape[0])])
    y = noisy(post, y, gen)
    finite = torch.isfinite(y).all(-1) & torch.isfinite(x).all(-1)
    report(int(x.shape[0]))
    return x[finite], y[finite], n, int(ok.sum())


def simulate_pairs(scene, params: TrainParams, *, callback=None, should_stop=None, rollout_batch: int = 0):
    """The training set (module docstring, step 1); ``rollout_batch``: starts simulated at once
    (0: a whole chunk; ``sizing.check_train_memory``), which does not change the set.

    Returns:
        x (N, P) starts, y (N, D) noisy observation vectors, and a dict (draws, feasible share,
        chunks, seconds).
    """
    from dejaview.parallel import map_chunks

    p = params
    t0 = time.perf_counter()
    xs, ys, draws, feasible, index = [], [], 0, 0, 0
    have = 0

    def report(_i, m):
        if callback is not None:
            callback({"phase": "simulate", "done": have + int(m), "total": p.simulations,
                      "elapsed_s": time.perf_counter() - t0})

    while have < p.simulations:
        share = feasible / draws if draws else 1.0
        if draws and share == 0:
            raise InferenceError(f"none of {draws} starts drawn from the prior is free of the other objects: "
                                 f"the start area cannot hold the source")
        need = math.ceil((p.simulations - have) / max(share, 1e-3) * (1.05 if draws else 1.0))
        chunks = [(index + i, p.chunk, p.seed, rollout_batch) for i in range(max(1, math.ceil(need / p.chunk)))]
        index += len(chunks)
        out = map_chunks(_chunk, chunks, setup=_setup, setup_args=(scene,), workers=p.workers, ray=p.ray,
                         on_report=report, should_stop=should_stop)
        if should_stop is not None and should_stop():
            raise InferenceError("stopped while simulating the training set")
        for x, y, n, ok in out:
            xs.append(x)
            ys.append(y)
            draws += n
            feasible += ok
            have += x.shape[0]
        if callback is not None:
            callback({"phase": "simulate", "done": min(have, p.simulations), "total": p.simulations,
                      "elapsed_s": time.perf_counter() - t0})
    x, y = torch.cat(xs)[:p.simulations], torch.cat(ys)[:p.simulations]
    return x, y, {"draws": draws, "feasible_share": feasible / max(draws, 1), "chunks": index,
                  "seconds": time.perf_counter() - t0}


def fit(post, x: torch.Tensor, y: torch.Tensor, params: TrainParams, *, callback=None, should_stop=None):
    """Fit the flow to pairs (x (N, P), y (N, D)) (module docstring, step 2).

    Returns:
        the ``AmortisedModel`` (its ``info`` without the scene's name) and the fit's record.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # measured: two threads beside another busy process ran a step 10-15x slower
    try:
        return _fit(post, x, y, params, callback, should_stop)
    finally:
        torch.set_num_threads(threads)


def _fit(post, x, y, params, callback, should_stop):
    from dejaview.inference.amortised.coordinates import to_flow
    from dejaview.inference.amortised.model import AmortisedModel, FlowShape, fingerprint

    p = params
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(int(p.seed) * 7 + 1)
    torch.manual_seed(int(p.seed))  # zuko's layers draw their initial weights from torch's global stream
    u = to_flow(post, x.to(torch.float64))
    u_mean, u_std = u.mean(0), u.std(0).clamp_min(1e-9)
    y_mean, y_std = y.mean(0), y.std(0).clamp_min(1e-9)
    f, c = (u - u_mean) / u_std, (y - y_mean) / y_std
    n = f.shape[0]
    perm = torch.randperm(n, generator=gen)
    n_val = max(1, int(p.validation * n))
    val, tr = perm[:n_val], perm[n_val:]
    if tr.numel() < 2:
        raise InferenceError(f"{n} training pairs are too few to fit a flow: ask for more simulations")
    shape = FlowShape(features=f.shape[1], context=c.shape[1], transforms=p.transforms, hidden=tuple(p.hidden),
                      bins=p.bins)
    flow = shape.build()
    opt = torch.optim.Adam(flow.parameters(), lr=p.lr)
    steps_per_epoch = math.ceil(tr.numel() / p.batch)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=p.epochs * steps_per_epoch)
    best, best_state, best_epoch, epoch = math.inf, None, -1, 0
    history = []
    for epoch in range(p.epochs):
        flow.train()
        order = tr[torch.randperm(tr.numel(), generator=gen)]
        total = 0.0
        for b in order.split(p.batch):
            loss = -flow(c[b]).log_prob(f[b]).mean()
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(flow.parameters(), 5.0)
            opt.step()
            sched.step()
            total += float(loss.detach()) * b.numel()
        flow.eval()
        with torch.no_grad():
            v = float(-flow(c[val]).log_prob(f[val]).mean())
        history.append((total / tr.numel(), v))
        if v < best:
            best, best_epoch = v, epoch
            best_state = {k: t.detach().clone() for k, t in flow.state_dict().items()}
        if callback is not None:
            callback({"phase": "fit", "epoch": epoch + 1, "epochs": p.epochs, "train_loss": total / tr.numel(),
                      "validation_loss": v, "elapsed_s": time.perf_counter() - t0})
        if epoch - best_epoch >= p.patience or time.perf_counter() - t0 > p.max_fit_seconds:
            break
        if should_stop is not None and should_stop():
            raise InferenceError("stopped while fitting the amortised posterior")
    if best_state is None:
        raise InferenceError("the flow's validation loss was never finite: the training set holds no usable pair")
    flow.load_state_dict(best_state)
    flow.eval()
    model = AmortisedModel(shape, flow, u_mean, u_std, y_mean, y_std, fingerprint(post), post.layout.names())
    model.set_reference(c[perm[:NEIGHBOURS]])
    record = {"epochs": epoch + 1, "best_epoch": best_epoch + 1, "validation_nll": best,
              "train_nll": history[best_epoch][0], "validation_pairs": int(n_val),
              "seconds": time.perf_counter() - t0}
    return model, record


def train(scene, params: TrainParams | None = None, *, callback=None, should_stop=None):
    """Train the amortised posterior of a scene (module docstring).

    Args:
        scene: a Scene (or a path) with ``<inference>`` and a ``<start-area>``.
        params: ``TrainParams``.
        callback: called with a dict (``phase`` simulate: ``done`` of ``total``; fit: ``epoch``,
            ``validation_loss``) as the work goes.
        should_stop: polled between chunks and epochs; True raises InferenceError.
    Returns:
        the ``AmortisedModel``; its ``info``: scene name, simulations, draws, feasible share,
        the fit's record, seconds.
    Raises:
        ResourceError: a training over ``params.memory_limit`` (``sizing.check_train_memory``),
            before any simulation.
    """
    from dejaview.geometry.collision import SceneCollision
    from dejaview.inference.amortised.coordinates import check_proper
    from dejaview.inference.posterior import Posterior
    from dejaview.inference.amortised.sizing import check_train_memory
    from dejaview.scene import Scene

    p = TrainParams() if params is None else params
    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    t0 = time.perf_counter()
    collision = SceneCollision(scene)
    post = Posterior.from_scene(scene, collision=collision).without_model()  # as ``_setup``, the collision kept
    check_proper(post)
    if post.layout.size == 0:
        raise InferenceError("the scene leaves nothing free to infer: free something in <optimize>")
    batch = check_train_memory(post, p, collision.query_bytes(scene.inference.source))
    x, y, sims = simulate_pairs(scene, p, callback=callback, should_stop=should_stop,
                                rollout_batch=0 if batch >= p.chunk else batch)
    model, record = fit(post, x, y, p, callback=callback, should_stop=should_stop)
    model.info = {"scene": scene.name or "the scene", "simulations": int(x.shape[0]), "seed": p.seed,
                  "draws": sims["draws"], "feasible_share": sims["feasible_share"],
                  "simulate_seconds": sims["seconds"], "fit": record, "seconds": time.perf_counter() - t0,
                  "flow": {"transforms": p.transforms, "hidden": list(p.hidden), "bins": p.bins}}
    return model


__all__ = ["fit", "simulate_pairs", "train"]
