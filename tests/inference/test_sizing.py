"""``dejaview.inference.sizing``: a sampler whose kernel density estimate alone does not fit gets it
in chunks; what does not fit even so is refused."""

from dejaview.inference.params import SizingParams
from dejaview.inference.sizing import kde_rows, sampler_bytes

MIN_KDE_ROWS = SizingParams().min_kde_rows


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


def test_sizing_params_are_checked():
    """The measured sizes are a frozen, checked ``SizingParams``: a size below 1 is a one-line error."""
    import dataclasses

    import pytest

    from dejaview.errors import InferenceError

    with pytest.raises(InferenceError, match="SizingParams.kde_copies"):
        SizingParams(kde_copies=0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        SizingParams().search_bytes = 1
    # a caller may size with other measurements: twice the matrices, twice the estimate's share
    candidate = 10_000
    small = sampler_bytes(16000, candidate)
    large = sampler_bytes(16000, candidate, sizing=SizingParams(kde_copies=10))
    assert large - small == 5 * 8 * 4000 * 4000
