"""``dejaview pack`` on the command line."""

from __future__ import annotations

import re

from click.testing import CliRunner

from dejaview.cli.pack import command
from dejaview.errors import GeometryError
from dejaview.geometry.packing import SpherePacking


def test_pack_writes_a_packing_and_reports_quality(tmp_path, box_mesh):
    mesh_path = tmp_path / "box.obj"
    box_mesh.export(mesh_path)
    out = tmp_path / "out.spheres"
    result = CliRunner().invoke(command, [str(mesh_path), "-n", "24", "-o", str(out),
                                          "--resolution", "0.008", "--quiet"])
    assert result.exit_code == 0, result.output
    packing = SpherePacking.read(out)
    assert 1 <= len(packing) <= 24
    assert packing.header["source"] == "box.obj"
    line = result.output.strip().splitlines()[-1]
    assert re.search(r"\d+ spheres, coverage \d+\.\d %, max outside \d+\.\d\d mm, "
                     r"max gap \d+\.\d\d mm, \d+\.\d s", line)


def test_pack_default_output_is_beside_the_mesh(tmp_path, box_mesh):
    mesh_path = tmp_path / "box.stl"
    box_mesh.export(mesh_path)
    result = CliRunner().invoke(command, [str(mesh_path), "-n", "4", "--resolution", "0.01"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "box.spheres").is_file()


def test_pack_missing_mesh_raises_a_geometry_error(tmp_path):
    result = CliRunner().invoke(command, [str(tmp_path / "none.obj")])
    assert isinstance(result.exception, GeometryError)
    assert "none.obj" in str(result.exception)


def test_pack_rejects_tolerance_above_2_mm(tmp_path):
    result = CliRunner().invoke(command, [str(tmp_path / "x.obj"), "--tolerance", "0.005"])
    assert result.exit_code == 2
    assert "tolerance" in result.output


def test_help_explains_the_options():
    result = CliRunner().invoke(command, ["--help"])
    assert result.exit_code == 0
    for option in ("--max-spheres", "--output", "--min-radius", "--coverage", "--tolerance",
                   "--quiet"):
        assert option in result.output
