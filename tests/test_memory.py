"""``dejaview.memory``: sizes, the limit and its override, and the one-line refusal."""

import pytest

from dejaview import memory
from dejaview.errors import ResourceError


@pytest.mark.parametrize("text, size", [("123456", 123456), ("512M", 512 * 2 ** 20), ("8g", 8 * 2 ** 30),
                                        ("1.5GiB", 3 * 2 ** 29), (" 2 KB ", 2048)])
def test_sizes_are_read_in_binary_units(text, size):
    assert memory.parse_size(text) == size


@pytest.mark.parametrize("text", ["", "-1G", "0", "lots", "12Q"])
def test_a_size_that_is_not_one_is_refused_in_one_line(text):
    with pytest.raises(ResourceError, match="DEJAVIEW_MEMORY_LIMIT=.* is not a size"):
        memory.parse_size(text)


def test_sizes_in_words():
    assert memory.format_size(19.1 * 2 ** 30) == "19.1 GiB"
    assert memory.format_size(512 * 2 ** 20) == "512 MiB"
    assert memory.format_size(22738 * 2 ** 40) == "22,738 TiB"
    assert memory.format_size(12) == "12 bytes"


def test_the_limit_is_a_share_of_the_machine_unless_the_environment_sets_it(monkeypatch):
    monkeypatch.delenv(memory.ENV, raising=False)
    limit, source = memory.limit()
    assert limit == int(memory.MACHINE_SHARE * memory.machine_bytes()) and "machine" in source
    monkeypatch.setenv(memory.ENV, "300M")
    assert memory.limit() == (300 * 2 ** 20, memory.ENV)


def test_a_request_over_the_limit_is_refused_naming_it_the_estimate_and_the_limit(monkeypatch):
    monkeypatch.setenv(memory.ENV, "4G")
    held = memory.resident()
    assert held > 0
    memory.check("a small request", 2 ** 20)  # fits: nothing raised
    with pytest.raises(ResourceError) as info:
        memory.check("5000000 posterior samples", 8 * 2 ** 30)
    message = str(info.value)
    assert message.startswith("5000000 posterior samples would need about ") and "\n" not in message
    assert "8 GiB for the request" in message and "over the limit of 4 GiB (DEJAVIEW_MEMORY_LIMIT)" in message
    assert info.value.need >= 8 * 2 ** 30 and info.value.limit == 4 * 2 ** 30
    renamed = info.value.naming("a heatmap of 2000 x 2000 cells")
    assert str(renamed).startswith("a heatmap of 2000 x 2000 cells would need about ")
    with pytest.raises(ResourceError, match="this server's limit for one job"):
        memory.check("a job", 2 ** 20, limit_bytes=held)
