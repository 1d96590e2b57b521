"""The viewer's routes without a browser: the built app at ``/``, ``/scenes`` and ``/files``."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from dejaview.server.app import create_app
from dejaview.server.viewer import STATIC_DIR

from .conftest import FIXTURES


@pytest.fixture
def client(tmp_path):
    root = tmp_path / "root"
    shutil.copytree(FIXTURES, root)
    (root / "notes.txt").write_text("not for the viewer")
    (root / ".hidden").mkdir()
    (root / ".hidden" / "x.xml").write_text('<scene version="1"/>')
    (root / "other.xml").write_text("<config/>")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.obj").write_text("v 0 0 0\n")
    (outside / "secret.xml").write_text('<scene version="1"/>')
    (root / "linked").symlink_to(outside, target_is_directory=True)
    (root / "meshes" / "env.obj").symlink_to(root / "notes.txt")
    with TestClient(create_app(scene_root=root, results_dir=tmp_path / "results", workers=1,
                               executor="thread")) as client:
        yield client


def test_the_built_viewer_is_in_the_package():
    """``npm run build`` in web/ writes these; they are committed, so pip install is all a user needs."""
    for name in ("index.html", "app.js", "style.css"):
        assert (STATIC_DIR / name).is_file(), f"{STATIC_DIR / name} is missing: run 'npm run build' in web/"
    assert "static/app.js" in (STATIC_DIR / "index.html").read_text()
    assert (STATIC_DIR / "app.js").stat().st_size > 100_000  # three.js is bundled in


def test_the_viewer_is_served_at_the_root(client):
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "DejaView" in page.text
    script = client.get("/static/app.js")
    assert script.status_code == 200 and "javascript" in script.headers["content-type"]
    assert client.get("/static/style.css").status_code == 200


def test_scenes_lists_scene_files_inside_the_root_only(client):
    assert client.get("/scenes").json()["scenes"] == ["scenes/arm.xml", "scenes/arm_moving.xml", "scenes/toss.xml"]


def test_scenes_lists_the_meshes_a_scene_can_add_with_their_packings(client):
    """The viewer's Add list: meshes of the scene root with the packing of the same name beside them
    or in a ``packings`` folder beside their folder; robots' meshes are their links, not objects."""
    assert client.get("/scenes").json()["meshes"] == [{"mesh": "meshes/cube.obj", "spheres": "packings/cube.spheres"}]


def test_files_serves_scenes_meshes_and_packings(client):
    assert client.get("/files/scenes/toss.xml").text.startswith("<?xml")
    assert client.get("/files/meshes/cube.obj").text.startswith("# DejaView")
    assert client.get("/files/scenes/../packings/cube.spheres").status_code == 200


@pytest.mark.parametrize("path, status, code", [
    ("notes.txt", 404, "not_found"),                 # not a scene, mesh or packing
    ("meshes/env.obj", 404, "not_found"),            # a link to another kind of file
    ("meshes/missing.obj", 404, "not_found"),
    ("linked/secret.obj", 400, "path_outside_root"),
    ("meshes/..%2F..%2Foutside/secret.obj", 400, "path_outside_root"),
    ("%2Fetc%2Fhostname.obj", 400, "path_outside_root"),
])
def test_files_refuses_everything_else(client, path, status, code):
    response = client.get(f"/files/{path}")
    assert response.status_code == status, response.text
    assert response.json()["code"] == code


def test_unknown_routes_still_answer_json_404(client):
    response = client.get("/no/such/route")
    assert response.status_code == 404 and response.json()["code"] == "not_found"


def test_robot_links_are_posed_by_the_server(client):
    got = client.get("/robot-links/scenes/arm.xml", params={"object": "arm"})
    assert got.status_code == 200, got.text
    links = got.json()["links"]
    assert [link["name"] for link in links] == ["arm/base", "arm/turret", "arm/upper_arm", "arm/forearm",
                                                "arm/hand"]
    assert links[0]["shape"] == "cylinder" and links[0]["position"] == pytest.approx([0, 0, 0.05])
    assert links[4]["shape"] == "mesh" and links[4]["mesh"] == "meshes/cube.obj"  # served by /files
    assert client.get("/files/" + links[4]["mesh"]).status_code == 200
    assert all("motion" not in link for link in links)  # it stands
    missing = client.get("/robot-links/scenes/arm.xml", params={"object": "floor"})
    assert missing.status_code == 404 and missing.json()["code"] == "not_found"
    outside = client.get("/robot-links/linked/secret.xml", params={"object": "arm"})
    assert outside.status_code == 400 and outside.json()["code"] == "path_outside_root"


def test_a_moving_robots_links_come_with_their_motion(client):
    """<joints time values>: each link's poses every 10 ms to the last keyframe, in the robot's frame,
    starting where the link stands (its pose), for the viewer's playback."""
    import math

    links = client.get("/robot-links/scenes/arm_moving.xml", params={"object": "arm"}).json()["links"]
    forearm = next(link for link in links if link["name"] == "arm/forearm")
    motion = forearm["motion"]
    assert motion["time"] == pytest.approx([0.01 * k for k in range(21)])
    assert motion["position"][0] == pytest.approx(forearm["position"], abs=1e-6)
    reach = 0.4 * math.cos(0.35) + 0.15  # the forearm's centre turns 1 rad about the base
    assert motion["position"][-1] == pytest.approx([reach * math.cos(1.0), reach * math.sin(1.0),
                                                    0.4 - 0.4 * math.sin(0.35)], abs=1e-6)
    assert motion["orientation"][10] == pytest.approx([math.cos(0.25), 0, 0, math.sin(0.25)], abs=1e-6)
