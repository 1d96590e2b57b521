"""The web viewer's routes: the built app at ``/``, the scenes of the scene root, and their files.

The viewer (sources in ``web/``, built by ``npm run build`` into ``dejaview/server/static``) is a
static three.js page; it lists scenes (and the meshes it can add to one) with ``GET /scenes``, reads a scene and its meshes and sphere
packings with ``GET /files/{path}``, and runs jobs over ``/ws``. ``/files`` serves only scene,
mesh and packing files, and only inside the scene root, with the same resolve-then-check as job
scenes (``dejaview.server.scenes``), so a default scene root of ``.`` exposes no other file.
"""

from __future__ import annotations

import html
import os
import urllib.parse
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

from dejaview.server.errors import ServiceError
from dejaview.server.scenes import inside, resolve_scene_path

STATIC_DIR = Path(__file__).resolve().parent / "static"
SERVED_SUFFIXES = {
    ".xml": "application/xml",
    ".obj": "text/plain",
    ".mtl": "text/plain",
    ".stl": "model/stl",
    ".ply": "application/octet-stream",
    ".glb": "model/gltf-binary",
    ".spheres": "text/plain",
}
MAX_LISTED = 2000
MAX_VISITED = 20_000  # files looked at: a huge scene root answers with what was found by then
SKIPPED_DIRS = {"node_modules", "__pycache__", "results"}


def list_scenes(root: Path, limit: int = MAX_LISTED) -> list[str]:
    """Scene files (``*.xml`` holding a ``<scene``) below ``root``, as sorted relative POSIX paths.

    Hidden folders and files, symlinks that lead outside the root and files that are not scenes
    are left out; at most ``limit`` entries, from at most ``MAX_VISITED`` files looked at.
    """
    found = []
    visited = 0
    for folder, dirs, files in os.walk(root, followlinks=False):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and d not in SKIPPED_DIRS)
        visited += len(files)
        if visited > MAX_VISITED:
            break
        for name in sorted(files):
            if name.startswith(".") or not name.lower().endswith(".xml"):
                continue
            path = Path(folder) / name
            if not inside(path, root):
                continue
            try:
                with open(path, "rb") as fh:
                    head = fh.read(4096)
            except OSError:
                continue
            if b"<scene" in head:
                found.append(path.relative_to(root).as_posix())
                if len(found) >= limit:
                    return sorted(found)
    return sorted(found)


MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb")
MAX_MESHES = 200


def list_meshes(root: Path, limit: int = MAX_MESHES) -> list[dict]:
    """Mesh files below ``root`` that the viewer can add to a scene: ``[{"mesh": path, "spheres": path
    or None}]`` (relative POSIX paths, sorted), ``spheres`` a packing of the same name beside the
    mesh or in a ``packings`` folder beside the mesh's folder (as ``examples/`` keeps them). The same
    walk and limits as ``list_scenes``; robot folders' meshes (a ``robots`` folder) are links of
    robots, not objects, and are left out."""
    found = []
    visited = 0
    for folder, dirs, files in os.walk(root, followlinks=False):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and d not in SKIPPED_DIRS and d != "robots")
        visited += len(files)
        if visited > MAX_VISITED:
            break
        for name in sorted(files):
            path = Path(folder) / name
            if name.startswith(".") or path.suffix.lower() not in MESH_SUFFIXES or not inside(path, root):
                continue
            if path.resolve().suffix.lower() not in MESH_SUFFIXES:  # a link to another kind of file
                continue
            packing = next((p for p in (path.with_suffix(".spheres"),
                                        path.parent.parent / "packings" / f"{path.stem}.spheres")
                            if p.is_file() and inside(p, root)), None)
            found.append({"mesh": path.relative_to(root).as_posix(),
                          "spheres": None if packing is None else packing.relative_to(root).as_posix()})
            if len(found) >= limit:
                break
        if len(found) >= limit:
            break
    return sorted(found, key=lambda m: m["mesh"])


def robot_link_geometry(root: Path, path: str, object_id: str) -> dict:
    """The collision geometry of robot ``object_id`` of the scene file ``path`` (inside ``root``), posed
    by forward kinematics in the robot's frame (its ``<pose>`` places the whole), for the viewer:
    ``{"object": id, "links": [{"name", "link", "shape", "size", "radius", "height", "mesh", "scale",
    "position", "orientation"}, ...]}``; ``mesh`` relative to the root (served by ``/files``). A moving
    robot's links (``<joints time values>``) also carry ``"motion": {"time": [...], "position": [[x, y,
    z], ...], "orientation": [[w, x, y, z], ...]}``, their poses every 10 ms to the last keyframe (the
    pose above is the first), which the viewer plays with the trajectory.

    Raises:
        ServiceError: the scene's checks (``dejaview.server.scenes``: files inside the root, the robot
            file read safely), ``not_found`` for an object that is not a robot of the scene.
    """
    from dataclasses import replace

    from dejaview.errors import SceneError
    from dejaview.geometry.robot import robot_pieces
    from dejaview.scene.model import Pose
    from dejaview.scene.xml import DEFAULT_MAX_BYTES
    from dejaview.server.scenes import read_scene_input

    scene = read_scene_input(root, scene_path=path, max_bytes=DEFAULT_MAX_BYTES).scene
    obj = next((o for o in scene.objects if o.id == object_id), None)
    if obj is None or obj.robot is None:
        raise ServiceError("not_found", f"{path!r} has no robot {object_id!r}", 404)
    try:
        pieces = robot_pieces(scene, replace(obj, pose=Pose()))
    except SceneError as exc:
        raise ServiceError("invalid_scene", f"{path}: {exc.reason}", 422) from None
    motion = {}
    if obj.moving:  # where each link is every MOTION_INTERVAL, for the viewer's playback
        from dejaview.io.mjcf_motion import MOTION_INTERVAL
        from dejaview.sim.motion import link_poses, sample_times

        times = sample_times(obj.keyframes[-1].time, MOTION_INTERVAL)
        try:
            poses = link_poses(scene, replace(obj, pose=Pose()), times)
        except SceneError as exc:
            raise ServiceError("invalid_scene", f"{path}: {exc.reason}", 422) from None
        motion = {name: {"time": times.tolist(), "position": pos.round(6).tolist(),
                         "orientation": quat.round(7).tolist()} for name, (pos, quat) in poses.items()}
    links = []
    for p in pieces:
        mesh = None if p.mesh is None else p.mesh.resolve().relative_to(root).as_posix()
        links.append({"name": p.name, "link": p.link, "shape": p.kind, "size": p.size, "radius": p.radius,
                      "height": p.height, "mesh": mesh, "scale": p.scale, "position": list(p.position),
                      "orientation": list(p.orientation)})
        if p.name in motion:
            links[-1]["motion"] = motion[p.name]
    return {"object": obj.id, "links": links}


def index_page(token: str | None) -> str:
    """``index.html``; with a token, its stylesheet and script URLs carry ``?token=`` so the
    browser can load them from a server that requires one (the page itself was opened as
    ``/?token=TOKEN``, and the script reads the token from that URL for its own requests)."""
    page = STATIC_DIR / "index.html"
    if not page.is_file():
        raise ServiceError("not_found", "the web viewer is not built: run 'npm run build' in web/", 404)
    text = page.read_text(encoding="utf-8")
    if token:
        query = html.escape(urllib.parse.urlencode({"token": token}))
        for name in ("static/app.js", "static/style.css"):
            text = text.replace(f'"{name}"', f'"{name}?{query}"')
    return text


def add_viewer_routes(app: FastAPI, root: Path, token: str | None = None) -> None:
    """``GET /``, ``/static/*``, ``GET /scenes`` and ``GET /files/{path}`` on ``app``.

    With a ``token`` every one of them needs it (``dejaview.server.access``): the browser opens
    ``/?token=TOKEN``, and the page it gets asks for its script and stylesheet with the token.
    """

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def index():
        # the page's URL holds the token: it must not leak through Referer or a shared cache
        headers = {"Referrer-Policy": "no-referrer", "Cache-Control": "no-store"} if token else None
        return HTMLResponse(index_page(token), headers=headers)

    @app.get("/scenes", summary="Scene files in the scene root, and the meshes a scene can add (for the "
                                "web viewer)")
    def scenes():
        return {"scenes": list_scenes(root), "meshes": list_meshes(root)}

    @app.get("/files/{path:path}", response_class=FileResponse,
             summary="A scene, mesh or sphere packing file inside the scene root")
    async def files(path: str):
        suffix = Path(path).suffix.lower()
        if suffix not in SERVED_SUFFIXES:
            raise ServiceError("not_found", f"{path!r}: only scene, mesh and packing files are served "
                                            f"({', '.join(sorted(SERVED_SUFFIXES))})", 404)
        try:
            resolved = resolve_scene_path(root, path)
        except ServiceError as exc:
            if exc.code == "scene_not_found":
                raise ServiceError("not_found", f"{path!r}: no such file in the scene root", 404) from None
            raise
        if resolved.suffix.lower() not in SERVED_SUFFIXES:  # a link to some other kind of file
            raise ServiceError("not_found", f"{path!r}: no such file in the scene root", 404)
        return FileResponse(resolved, media_type=SERVED_SUFFIXES[suffix])

    @app.get("/robot-links/{path:path}", summary="A robot's link geometry in a scene of the scene root "
                                                 "(for the web viewer)")
    def robot_links(path: str, object: str):
        return robot_link_geometry(root, path, object)

    if STATIC_DIR.is_dir():
        app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
