"""``dejaview client`` against the real server, and ``dejaview serve`` options."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import urllib.error
import urllib.request

from click.testing import CliRunner

from dejaview.cli import SUBCOMMANDS, cli

from .conftest import FIXTURES


def run_cli(*args, timeout=180):
    return subprocess.run([sys.executable, "-m", "dejaview", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def test_serve_and_client_are_subcommands():
    assert SUBCOMMANDS["serve"] == "dejaview.cli.serve" and SUBCOMMANDS["client"] == "dejaview.cli.client"
    runner = CliRunner()
    for name in ("serve", "client"):
        result = runner.invoke(cli, [name, "--help"])
        assert result.exit_code == 0 and "Usage:" in result.output
    assert "--scene-root" in runner.invoke(cli, ["serve", "--help"]).output


def test_client_solves_a_local_scene_file(live_server, tmp_path):
    result = run_cli("client", FIXTURES / "ball.xml", "--kind", "solve", "--url", live_server.ws_url,
                     "-o", tmp_path, "--iterations", "2")
    assert result.returncode == 0, result.stderr
    assert "done" in result.stdout and "best loss" in result.stdout
    assert json.loads((tmp_path / "result.json").read_text())["source"] == "ball"
    assert (tmp_path / "trajectory.csv").read_text().startswith("step,time,object")


def test_client_with_a_scene_path(live_server, tmp_path):
    result = run_cli("client", "drop.xml", "--scene-path", "--kind", "simulate", "--url", live_server.ws_url,
                     "-o", tmp_path, "--quiet")
    assert result.returncode == 0, result.stderr
    assert result.stdout == "" and (tmp_path / "trajectory.csv").is_file()


def test_client_errors_are_one_line(live_server, tmp_path):
    cases = [
        (["drop.xml", "--scene-path", "--kind", "solve"], "invalid_scene: the scene has no <inference>"),
        (["../outside/secret.xml", "--scene-path", "--kind", "simulate"], "path_outside_root"),
        (["drop.xml", "--scene-path", "--kind", "simulate", "--iterations", "3"], "does not apply"),
        ([FIXTURES / "nothing.xml", "--kind", "simulate"], "cannot read"),
    ]
    for args, fragment in cases:
        result = run_cli("client", *args, "--url", live_server.ws_url, "-o", tmp_path)
        assert result.returncode != 0
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0], result.stderr
    result = run_cli("client", "drop.xml", "--scene-path", "--url", "ws://127.0.0.1:9/ws", "-o", tmp_path)
    assert result.returncode != 0 and result.stderr.startswith("error: cannot connect")


def test_client_timeout_exits_non_zero(live_server, tmp_path):
    """``--timeout`` ends the wait with a non-zero exit and one line naming the job; the job (which
    cannot finish first) is then cancelled to free the shared server's worker. Should it have
    finished all the same, the cancel gets 409 and the job must be done, not lost."""
    scene = FIXTURES / "solve_endless.xml"  # minutes where the timeout is 2 s
    result = run_cli("client", scene, "--url", live_server.ws_url, "-o", tmp_path / "out", "--timeout", "2")
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    match = re.fullmatch(r"error: job (\S+) not done after 2 s", lines[-1]) if len(lines) == 1 else None
    assert match and match.group(1) != "None", result.stderr
    url = f"{live_server.http_url}/jobs/{match.group(1)}"
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method="DELETE"), timeout=30) as response:
            assert response.status == 202
    except urllib.error.HTTPError as exc:  # finished in between: it must have finished well
        assert exc.code == 409
        with urllib.request.urlopen(url, timeout=30) as response:
            assert json.loads(response.read())["state"] == "done"
