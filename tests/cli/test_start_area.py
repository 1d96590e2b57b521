"""Issue 56: ``dejaview solve`` and ``dejaview heatmap`` refuse a start area that cannot hold the
source with validate's kind of one-line error, exit status 2, and write nothing."""

from pathlib import Path

import pytest

from .test_cli import run_cli

BOX_IN_DESK = Path(__file__).resolve().parents[1] / "fixtures" / "inference" / "box_in_desk.xml"


@pytest.mark.parametrize("command", ["solve", "heatmap"])
def test_a_start_area_inside_the_desk_exits_2_with_one_line_and_writes_nothing(tmp_path, command):
    out = tmp_path / "out"
    result = run_cli(command, BOX_IN_DESK, "-o", out)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"error: {BOX_IN_DESK}:")
    assert "<start-area> (-0.2, -0.1, 0.7233) to (0.2, 0.1, 0.7233) cannot hold 'src': everywhere in it " \
           "'src' and 'desk' interpenetrate, by 0.0267 m" in lines[0]
    assert result.stdout == ""
    assert not out.exists()
