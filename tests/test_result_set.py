"""``dejaview.result_set``: a result set is written whole or not at all."""

import errno

import pytest

from dejaview.errors import OutputError
from dejaview.result_set import partial_folders, write_result_set

NAMES = ("result.json", "iterations.csv", "posterior.csv")


def writer(text, with_posterior=False):
    def write(folder):
        out = {}
        for name in NAMES[:3 if with_posterior else 2]:
            with open(folder / name, "w") as fh:
                fh.write(f"{name} {text}")
            out[name] = folder / name
        return out
    return write


def test_a_new_folder_is_the_whole_set(tmp_path):
    paths = write_result_set(tmp_path / "a" / "out", writer("one"), NAMES)
    assert paths == {name: tmp_path / "a" / "out" / name for name in NAMES[:2]}
    assert (tmp_path / "a" / "out" / "iterations.csv").read_text() == "iterations.csv one"
    assert partial_folders(tmp_path / "a" / "out") == []


def test_a_set_replaces_the_earlier_one_keeps_other_files_and_drops_its_stale_ones(tmp_path):
    out = tmp_path / "out"
    write_result_set(out, writer("one", with_posterior=True), NAMES)
    (out / "notes.txt").write_text("mine")
    write_result_set(out, writer("two"), NAMES)
    assert sorted(p.name for p in out.iterdir()) == ["iterations.csv", "notes.txt", "result.json"]
    assert (out / "result.json").read_text() == "result.json two"


@pytest.mark.parametrize("earlier", [False, True])
def test_a_full_disk_leaves_the_earlier_set_or_nothing_and_one_line(tmp_path, disk_full_at, earlier):
    out = tmp_path / "out"
    if earlier:
        write_result_set(out, writer("one", with_posterior=True), NAMES)
    before = {p.name: p.read_text() for p in out.iterdir()} if earlier else None
    disk_full_at("iterations.csv")  # result.json is written, then the disk is full
    with pytest.raises(OutputError) as info:
        write_result_set(out, writer("two"), NAMES)
    message = str(info.value)
    assert message.startswith(f"cannot write {out / 'iterations.csv'}: No space left on device (the disk is "
                              f"full); the result set was not written")
    assert "\n" not in message and info.value.errno == errno.ENOSPC
    assert message.endswith("keeps what it held)" if earlier else "was not created)")
    if earlier:
        assert {p.name: p.read_text() for p in out.iterdir()} == before
    else:
        assert not out.exists()
    assert partial_folders(out) == []


def test_a_writer_that_fails_otherwise_leaves_nothing_behind(tmp_path):
    def broken(folder):
        (folder / "result.json").write_text("{}")
        raise ValueError("a bug")

    with pytest.raises(ValueError):
        write_result_set(tmp_path / "out", broken)
    assert list(tmp_path.iterdir()) == []
