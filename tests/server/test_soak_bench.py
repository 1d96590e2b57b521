"""``dejaview bench soak``'s full disk: it falls between the kills, and the filler leaves no room."""

import subprocess
import sys

import pytest

from dejaview.cli.bench import bench_module
from tests.conftest import needs_mount_namespace


def test_the_disk_is_full_in_the_middle_of_the_longest_stretch_without_a_kill():
    soak = bench_module("soak")
    assert soak.full_window([10.0, 20.0, 50.0], 60.0) == (27.5, 42.5)  # 20-50 s: its middle half
    assert soak.full_window([], 600.0) == (270.0, 330.0)  # at most FULL_S = 60 s


@needs_mount_namespace()
def test_the_filler_leaves_no_room_on_a_small_disk_and_its_removal_frees_it(tmp_path):
    """A 1 MiB tmpfs: after ``fill_disk`` one byte more is ENOSPC; without the filler it is written.
    Skipped where no mount namespace can be had (``needs_mount_namespace``): the soak then runs
    without filling the disk and says so."""
    path = bench_module("soak").__file__
    code = ("import errno, importlib.util, os, sys; from pathlib import Path; "
            f"spec = importlib.util.spec_from_file_location('soak', {path!r}); "
            "soak = importlib.util.module_from_spec(spec); spec.loader.exec_module(soak); d = Path(sys.argv[1]); "
            "print(soak.fill_disk(d)); fd = os.open(d / 'x', os.O_WRONLY | os.O_CREAT)\n"
            "try:\n    os.write(fd, b'1'); print('written')\n"
            "except OSError as e:\n    print(errno.errorcode[e.errno])\n"
            "(d / soak.FILLER).unlink(); print(os.write(fd, b'1'))")
    script = 'mount -t tmpfs -o size=1m tmpfs "$1" && exec "$0" -c "$2" "$1"'
    result = subprocess.run(["unshare", "-rm", "sh", "-c", script, sys.executable, str(tmp_path), code],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    filled, full, freed = result.stdout.split()
    assert int(filled) > 900_000 and full == "ENOSPC" and freed == "1"
