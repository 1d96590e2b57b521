"""The memory a solve holds, sized before it runs (``dejaview.memory``).

A solve's memory grows with its posterior samples: the sampler simulates a run's particles as one
batch, and its population move weighs half of them against the other half (a kernel density
estimate: quadratic in the particles). Where that estimate does not fit but the rest does, it is
computed a chunk of particles at a time (``kde_rows``: the same numbers, linear in the
particles); ``check_solve_memory`` refuses samples the limit cannot hold even so, in one line,
before the search. The constants are measured peaks (docs/benchmarks.md, "Sized
before run"), rounded up.
"""

from __future__ import annotations

from dejaview.inference.sampling import particles

SEARCH_BYTES = 128 * 2 ** 20
"""Memory the default search holds at its peak beyond the built problem: 58 MiB (ball_down_ramp) and 82 MiB (mug_off_counter) measured at the
default budget, with room to spare."""
ROLLOUT_COPIES = 3
"""Records' worth of memory a candidate of a batch of rollouts holds at the batch's peak (2.4
measured: a batch of 4000 on box_among_boxes, 751 records of 4 bodies)."""
KDE_COPIES = 5
"""(M, M) float64 matrices ``_SMC.population_move`` holds at its peak for M guides (4.1-4.3
measured: the kernels, cdist's distances and their square)."""
PARTICLE_BYTES = 16384
"""The rest a particle holds (its state, the moves' proposals, ``torch.unique``'s copies), from the
peak of ``dejaview solve ball_down_ramp.xml --samples 8000`` (docs/benchmarks.md, "Sized before
run") less the kernels and the batch."""


def candidate_bytes(problem, variants: int = 1, start_bytes: int = 0) -> int:
    """Bytes one candidate of a batch of rollouts of the spheres ``problem`` holds at the batch's peak:
    its recorded states (13 numbers per body and record, ``ROLLOUT_COPIES`` times, once per
    physics variant) and ``start_bytes`` of its interpenetration check
    (``SceneCollision.query_bytes``)."""
    records = problem.steps // max(problem.record_every, 1) + 2
    return ROLLOUT_COPIES * records * problem.world.num_bodies * 13 * 8 * variants + start_bytes


MIN_KDE_ROWS = 64
"""Fewest particles a chunk of the kernel density estimate holds: below it, refused."""


def sampler_bytes(n: int, candidate: int, kde_rows: int = 0) -> int:
    """Bytes ``Sampler.sample`` for n samples holds at its peak beyond what its process held before,
    ``candidate`` bytes per candidate rollout (``candidate_bytes``): one run's particles, each with
    a rollout and ``PARTICLE_BYTES``, and the kernel density estimate of half of them against the
    other half (``KDE_COPIES`` matrices: quadratic in the particles), ``kde_rows`` particles of
    the half at a time (0: all)."""
    size = max(particles(n))
    half = size - size // 2
    rows = min(kde_rows, half) if kde_rows else half
    return size * (candidate + PARTICLE_BYTES) + KDE_COPIES * 8 * rows * half


def kde_rows(n: int, candidate: int, room: int) -> int:
    """Particles the kernel density estimate of a sampler for n samples takes at a time so that the
    sampler fits in ``room`` bytes (``sampler_bytes``): 0 (all at once) where it fits whole, else
    the most that fit, at least ``MIN_KDE_ROWS``."""
    if sampler_bytes(n, candidate) <= room:
        return 0
    size = max(particles(n))
    row = KDE_COPIES * 8 * (size - size // 2)  # one particle's row of the estimate
    return max(MIN_KDE_ROWS, (room - sampler_bytes(n, candidate, kde_rows=1) + row) // row)


def check_solve_memory(scene, problem, samples: int, collision, memory_limit: int | None):
    """Refuse a solve (the default search, then ``samples`` posterior samples) that the memory limit
    (``memory_limit`` bytes, None: ``dejaview.memory.limit()``) cannot hold even with its kernel
    density estimate in chunks (``kde_rows``), before it runs.

    Args:
        scene: the Scene; problem: its built spheres problem; samples: posterior samples (>= 1);
        collision: the scene's ``SceneCollision`` if one was built (else built here to size the
            interpenetration checks).
    Returns:
        The scene's ``SceneCollision`` (for the search to reuse), and the sampler's
        ``SamplerParams.kde_rows`` (0: the estimate fits whole).
    Raises:
        ResourceError: one line naming the samples, the estimate and the limit.
    """
    from dejaview import memory
    from dejaview.geometry.collision import SceneCollision
    from dejaview.inference.model_uncertainty import ModelVariants

    inner = problem
    collision = SceneCollision(scene) if collision is None else collision
    model = ModelVariants.from_scene(scene, inner.world)
    candidate = candidate_bytes(inner, 1 if model is None else model.count,
                                collision.query_bytes(scene.inference.source))
    room = (memory.limit()[0] if memory_limit is None else memory_limit) - memory.resident() - SEARCH_BYTES
    rows = kde_rows(samples, candidate, room)
    memory.check(f"{samples} posterior samples", SEARCH_BYTES + sampler_bytes(samples, candidate, rows),
                 memory_limit)
    return collision, rows
