"""The memory a solve holds, sized before it runs (``dejaview.memory``).

A solve's memory grows with its posterior samples: the sampler simulates a run's particles as one
batch, and its population move weighs half of them against the other half (a kernel density
estimate: quadratic in the particles). Where that estimate does not fit but the rest does, it is
computed a chunk of particles at a time (``kde_rows``: the same numbers, linear in the
particles); ``check_solve_memory`` refuses samples the limit cannot hold even so, in one line,
before the search. The sizes are measured peaks, rounded up (``SizingParams``).

An amortised training is sized alike (``dejaview.inference.amortised.sizing``), with
``candidate_bytes`` for its rollouts.
"""

from __future__ import annotations

from dejaview.inference.params import SizingParams
from dejaview.inference.sampling import particles
from dejaview.sim.state import STATE_WIDTH


def candidate_bytes(problem, variants: int = 1, start_bytes: int = 0,
                    sizing: SizingParams = SizingParams()) -> int:
    """Bytes one candidate of a batch of rollouts of the spheres ``problem`` holds at the batch's peak:
    its recorded states (``STATE_WIDTH`` numbers per body and record, ``sizing.rollout_copies``
    times, once per physics variant) and ``start_bytes`` of its interpenetration check
    (``SceneCollision.query_bytes``)."""
    records = problem.steps // max(problem.record_every, 1) + 2
    return (sizing.rollout_copies * records * problem.world.num_bodies * STATE_WIDTH * 8 * variants
            + start_bytes)


def sampler_bytes(n: int, candidate: int, kde_rows: int = 0, sizing: SizingParams = SizingParams()) -> int:
    """Bytes ``Sampler.sample`` for n samples holds at its peak beyond what its process held before,
    ``candidate`` bytes per candidate rollout (``candidate_bytes``): one run's particles, each with
    a rollout and ``sizing.particle_bytes``, and the kernel density estimate of half of them against
    the other half (``sizing.kde_copies`` matrices: quadratic in the particles), ``kde_rows``
    particles of the half at a time (0: all)."""
    size = max(particles(n))
    half = size - size // 2
    rows = min(kde_rows, half) if kde_rows else half
    return size * (candidate + sizing.particle_bytes) + sizing.kde_copies * 8 * rows * half


def kde_rows(n: int, candidate: int, room: int, sizing: SizingParams = SizingParams()) -> int:
    """Particles the kernel density estimate of a sampler for n samples takes at a time so that the
    sampler fits in ``room`` bytes (``sampler_bytes``): 0 (all at once) where it fits whole, else
    the most that fit, at least ``sizing.min_kde_rows``."""
    if sampler_bytes(n, candidate, sizing=sizing) <= room:
        return 0
    size = max(particles(n))
    row = sizing.kde_copies * 8 * (size - size // 2)  # one particle's row of the estimate
    return max(sizing.min_kde_rows, (room - sampler_bytes(n, candidate, kde_rows=1, sizing=sizing) + row) // row)


def check_solve_memory(scene, problem, samples: int, collision, memory_limit: int | None,
                       sizing: SizingParams = SizingParams()):
    """Refuse a solve (the default search, then ``samples`` posterior samples) that the memory limit
    (``memory_limit`` bytes, None: ``dejaview.memory.limit()``) cannot hold even with its kernel
    density estimate in chunks (``kde_rows``), before it runs.

    Args:
        scene: the Scene; problem: its built spheres problem; samples: posterior samples (>= 1);
        collision: the scene's ``SceneCollision`` if one was built (else built here to size the
            interpenetration checks); sizing: the measured sizes the estimate is made of.
    Returns:
        The scene's ``SceneCollision`` (for the search to reuse), and the sampler's
        ``SamplerParams.kde_rows`` (0: the estimate fits whole).
    Raises:
        ResourceError: one line naming the samples, the estimate and the limit.
    """
    from dejaview import memory
    from dejaview.geometry.collision import SceneCollision
    from dejaview.inference.model_uncertainty import ModelVariants

    collision = SceneCollision(scene) if collision is None else collision
    model = ModelVariants.from_scene(scene, problem.world)
    candidate = candidate_bytes(problem, 1 if model is None else model.count,
                                collision.query_bytes(scene.inference.source), sizing)
    room = (memory.limit()[0] if memory_limit is None else memory_limit) - memory.resident() - sizing.search_bytes
    rows = kde_rows(samples, candidate, room, sizing)
    memory.check(f"{samples} posterior samples",
                 sizing.search_bytes + sampler_bytes(samples, candidate, rows, sizing), memory_limit)
    return collision, rows
