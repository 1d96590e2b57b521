"""``dejaview.inference.sizing``: a sampler whose kernel density estimate alone does not fit gets it
in chunks; what does not fit even so is refused."""

from dejaview.inference.sizing import MIN_KDE_ROWS, kde_rows, sampler_bytes


def test_the_estimate_is_chunked_where_only_it_does_not_fit():
    """16000 samples: two runs of 8000 particles, the estimate 4000 x 4000 (610 MiB of its 812)."""
    candidate = 10_000
    whole = sampler_bytes(16000, candidate)
    assert kde_rows(16000, candidate, whole) == 0  # fits whole: all at once
    room = whole // 2
    rows = kde_rows(16000, candidate, room)
    assert MIN_KDE_ROWS < rows < 4000
    assert sampler_bytes(16000, candidate, rows) <= room < sampler_bytes(16000, candidate, rows + 1)
    # the particles alone over the room: the fewest rows, whose estimate the memory check refuses
    least = sampler_bytes(16000, candidate, MIN_KDE_ROWS)
    assert kde_rows(16000, candidate, least - 1) == MIN_KDE_ROWS
    assert sampler_bytes(16000, candidate, 10 ** 9) == whole
