"""The memory an amortised training holds, sized before it runs (``dejaview.memory``).

An amortised training (``dejaview train``, the service's ``train`` jobs) holds its training set,
one batch of rollouts (``dejaview.inference.sizing.candidate_bytes`` each) and the flow's fit
(``train_bytes``). Where a whole chunk's rollouts do not fit but the rest does, they are simulated
a smaller batch at a time (the same training set, each rollout being independent of its batch);
``check_train_memory`` refuses a training the limit cannot hold even so, in one line, before any
simulation. The sizes are measured peaks, rounded up (``SizingParams``).
"""

from __future__ import annotations

import math

from dejaview.inference.params import SizingParams
from dejaview.inference.sizing import candidate_bytes


def flow_bytes(post, params, sizing: SizingParams = SizingParams()) -> int:
    """Bytes the fit of ``params``' flow (``TrainParams``: its shape, batch, validation share) holds
    for ``post``'s P parameters and D observation numbers at its peak, beyond the training set: the
    parameters ``sizing.flow_copies`` times, a batch's activations through every transform
    (``sizing.activation_copies``), the validation pairs' through one (``sizing.validation_copies``),
    and ``sizing.fit_bytes``."""
    import torch

    from dejaview.inference.amortised.model import FlowShape
    from dejaview.inference.amortised.observables import width

    shape = FlowShape(features=post.layout.size, context=width(post), transforms=params.transforms,
                      hidden=tuple(params.hidden), bins=params.bins)
    with torch.random.fork_rng(devices=[]):  # the flow's initial weights draw from torch's global stream
        count = sum(t.numel() for t in shape.build().parameters())
    row = 8 * (sum(shape.hidden) + shape.features * 3 * shape.bins)  # one pair's through one transform
    batch = params.batch * params.transforms * sizing.activation_copies * row
    validation = math.ceil(params.validation * params.simulations) * sizing.validation_copies * row
    return sizing.flow_copies * 8 * count + batch + validation + sizing.fit_bytes


def train_bytes(post, params, candidate: int, batch: int, sizing: SizingParams = SizingParams()) -> int:
    """Bytes a training of ``post`` (a ``Posterior``) with ``params`` (``TrainParams``) holds at its
    peak beyond what its process held before: the training set (``params.simulations`` starts of P
    and observation vectors of D float64 numbers, ``sizing.pair_copies`` times), ``batch`` rollouts
    of ``candidate`` bytes each (``candidate_bytes``) and the flow's fit (``flow_bytes``)."""
    from dejaview.inference.amortised.observables import width

    pairs = sizing.pair_copies * 8 * params.simulations * (post.layout.size + width(post))
    return pairs + batch * candidate + flow_bytes(post, params, sizing)


def check_train_memory(post, params, start_bytes: int = 0, sizing: SizingParams = SizingParams()) -> int:
    """Refuse a training (``params``: ``TrainParams``, its ``memory_limit`` bytes, None:
    ``dejaview.memory.limit()``) that the limit cannot hold even with its rollouts simulated
    ``sizing.min_rollout_batch`` at a time, before any simulation.

    Args:
        post: the scene's ``Posterior`` (its own physics); start_bytes: the interpenetration check
            of one start (``SceneCollision.query_bytes``).
    Returns:
        Starts whose rollouts are simulated at once (``TrainParams.chunk``: a whole chunk; fewer
        where a chunk's do not fit).
    Raises:
        ResourceError: one line naming the simulations, the estimate and the limit.
    """
    from dejaview import memory

    limit = memory.limit()[0] if params.memory_limit is None else params.memory_limit
    candidate = candidate_bytes(post.problem, 1, start_bytes, sizing)
    fixed = train_bytes(post, params, candidate, 0, sizing)
    room = limit - memory.resident() - fixed
    batch = max(min(params.chunk, sizing.min_rollout_batch), min(params.chunk, room // candidate))
    memory.check(f"{params.simulations} training simulations", fixed + batch * candidate, params.memory_limit)
    return batch
