"""Scenes a client may run: XML text or a file inside the scene root, and nothing outside it.

Every path is resolved (symlinks included) before it is used and must land
inside the scene root: ``scene_path`` itself, every ``mesh``/``spheres``/
``urdf``/``mjcf`` file the scene names and every mesh a URDF names, whether the scene came as text (relative names resolve
against the scene root) or as a file (they resolve against its folder, as
everywhere else). Files outside the root are refused before anything checks
whether they exist, so the server answers no questions about the rest of the
disk. The XML reader itself (``dejaview.scene.xml``) refuses DTDs and
entities, network access and oversized documents.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath

from dejaview.errors import SceneError
from dejaview.scene.bounds import default_substeps
from dejaview.server.errors import ServiceError

SCENE_XML_NAME = "<scene_xml>"


@dataclass(frozen=True)
class SceneInput:
    """A checked scene and where it came from.

    Attributes:
        scene: the parsed Scene.
        text: the XML text (what a worker parses again).
        base_dir: folder relative file names resolve against.
        filename: name used in error messages (``<scene_xml>`` or the relative path).
        source: for the job record: ``{"scene_path": ...}`` or ``{"scene_xml": "<N bytes>"}``.
    """

    scene: object
    text: str
    base_dir: Path
    filename: str
    source: dict


def inside(path: Path, root: Path) -> bool:
    """True when ``path``, with every symlink resolved, is ``root`` or below it."""
    try:
        return path.resolve().is_relative_to(root)
    except (OSError, RuntimeError, ValueError):  # symlink loops, NUL bytes
        return False


def resolve_scene_path(root: Path, name: str) -> Path:
    """The file ``name`` (relative to ``root``) names, after every check.

    Raises:
        ServiceError: ``path_outside_root`` for absolute paths and anything that resolves
            outside the root (``..``, symlinks); ``scene_not_found`` when no such file.
    """
    if not isinstance(name, str) or not name.strip() or "\x00" in name:
        raise ServiceError("scene_not_found", "scene_path must name a file in the scene root")
    if PurePosixPath(name).is_absolute() or PureWindowsPath(name).is_absolute() or \
            PureWindowsPath(name).drive:
        raise ServiceError("path_outside_root",
                           f"scene_path {name!r} is absolute: give a path relative to the scene root")
    candidate = root / name
    if not inside(candidate, root):
        raise ServiceError("path_outside_root", f"scene_path {name!r} leads outside the scene root")
    resolved = candidate.resolve()
    try:
        ok = resolved.is_file()
    except OSError:
        ok = False
    if not ok:
        raise ServiceError("scene_not_found", f"scene_path {name!r}: no such file in the scene root")
    return resolved


def check_files(scene, root: Path, filename: str) -> None:
    """Every mesh, sphere, URDF and MJCF file of ``scene``, and every mesh a URDF names, must resolve
    inside ``root`` and exist; then a robot's file is read (hardened XML: no DTD, no entities) and
    its joints checked.

    Raises:
        ServiceError: ``path_outside_root``.
        SceneError: a file inside the root that does not exist, a robot file or joints that do not fit.
    """
    for obj in scene.objects:
        for attr in ("mesh", "spheres", "urdf", "mjcf"):
            name = getattr(obj, attr)
            if name is None:
                continue
            path = scene.resolve(name)
            if not inside(path, root):
                raise ServiceError("path_outside_root",
                                   f"{filename}: object {obj.id!r}: {attr} {name!r} leads outside the "
                                   f"scene root")
            if not path.resolve().is_file():
                raise SceneError(f"{attr} file {name!r} not found in the scene root", filename,
                                 obj.line, "object")
        if getattr(obj, "robot", None) is not None:
            _check_robot(scene, obj, root, filename)


def _check_robot(scene, obj, root: Path, filename: str) -> None:
    """A robot's file read, the meshes it names inside ``root`` and present, its joints in limits."""
    from dejaview.geometry.robot import joint_problems, robot_model

    from dejaview.geometry.mjcf_files import MeshOutsideRoot

    try:
        model = robot_model(scene, obj)
    except MeshOutsideRoot as exc:  # refused unread; what it names outside is not shown
        raise ServiceError("path_outside_root", f"{filename}: object {obj.id!r}: {obj.robot!r} names a file "
                                                "that leads outside the scene root") from None
    except SceneError as exc:  # located in the robot file, shown relative to the root
        where = _shown(Path(exc.file), root) if exc.file else obj.robot
        where += f":{exc.line}" if exc.line else ""
        element = f" <{exc.element}>" if exc.element else ""
        raise SceneError(f"object {obj.id!r}: {where}:{element} {exc.reason}", filename, obj.line,
                         "object") from None
    for path in model.files:
        if not inside(path, root):
            raise ServiceError("path_outside_root", f"{filename}: object {obj.id!r}: {obj.robot!r} names mesh "
                                                    f"{_shown(path, root)!r}, which leads outside the scene root")
        if not path.resolve().is_file():
            raise SceneError(f"mesh file {_shown(path, root)!r} named by {obj.robot!r} not found in the scene root",
                             filename, obj.line, "object")
    problems = joint_problems(model, obj.joints) if obj.joints is not None or not obj.keyframes else []
    for frame in obj.keyframes:  # a moving robot's keyframes, as dejaview.scene.validate checks them
        problems += joint_problems(model, frame.values, what=f"<joints time=\"{frame.time:g}\">")
    if problems:
        raise SceneError(f"robot {obj.id!r}: {problems[0]}", filename, obj.line, "object")


def _shown(path: Path, root: Path) -> str:
    """A path as a client may see it: relative to the root where it is inside, else its name only."""
    try:
        return Path(os.path.normpath(Path(path).absolute())).relative_to(root).as_posix()
    except ValueError:
        return Path(path).name


def read_scene_input(root: Path, *, scene_xml: str | None = None, scene_path: str | None = None,
                     max_bytes: int) -> SceneInput:
    """Read and check the scene of a job request (exactly one of ``scene_xml``, ``scene_path``).

    Raises:
        ServiceError: ``scene_too_large``, ``scene_not_found``, ``path_outside_root``,
            ``invalid_scene`` (the reader's one-line ``file:line: <element> reason``).
    """
    from dejaview.scene.xml import read_scene_string

    if scene_xml is not None:
        data = scene_xml.encode("utf-8", errors="surrogatepass")
        filename, base_dir = SCENE_XML_NAME, root
        source = {"scene_xml": f"<{len(data)} bytes>"}
    else:
        path = resolve_scene_path(root, scene_path)
        try:
            with open(path, "rb") as fh:
                data = fh.read(max_bytes + 1)
        except OSError as exc:
            raise ServiceError("scene_not_found",
                               f"scene_path {scene_path!r}: cannot read: {exc.strerror}") from None
        filename, base_dir = os.path.normpath(scene_path), path.parent
        source = {"scene_path": filename}
    if len(data) > max_bytes:
        size = f"{len(data)} bytes" if scene_xml is not None else f"over {max_bytes} bytes"
        raise ServiceError("scene_too_large", f"{filename}: the scene is {size}, over the limit of "
                                              f"{max_bytes} bytes", 413)
    try:
        # files are checked here, after the root check, so no file outside the root is ever looked at
        scene = read_scene_string(data, base_dir=base_dir, filename=filename, max_bytes=max_bytes,
                                  check_files=False, root=root)
        check_files(scene, root, filename)
        text = data.decode("utf-8")
    except SceneError as exc:
        raise ServiceError("invalid_scene", str(exc), 422) from None
    except UnicodeDecodeError:
        raise ServiceError("invalid_scene", f"{filename}: the scene is not UTF-8 text", 422) from None
    return SceneInput(scene=scene, text=text, base_dir=base_dir, filename=filename, source=source)


def check_job(kind: str, scene, overrides: dict, config) -> None:
    """Refuse jobs the scene cannot answer or that are bigger than the server allows.

    Raises:
        ServiceError: ``invalid_scene`` (no ``<inference>`` / ``<start-area>``) or
            ``limit_exceeded`` (a ``train`` job's ``simulations`` too).
    """
    if len(scene.objects) > config.max_objects:
        raise ServiceError("limit_exceeded", f"the scene has {len(scene.objects)} objects, over the "
                           f"server's limit of {config.max_objects}", 422)
    inf = scene.inference
    if kind in ("solve", "heatmap", "train") and inf is None:
        raise ServiceError("invalid_scene", f"the scene has no <inference> section: nothing to {kind}",
                           422)
    if kind in ("heatmap", "train") and inf.start_area is None:
        what = "a heatmap" if kind == "heatmap" else "an amortised model (train, live)"
        raise ServiceError("invalid_scene", f"{what} needs an <inference> with a <start-area>", 422)
    if kind == "train" and overrides.get("simulations", 0) > config.max_train_simulations:
        raise ServiceError("limit_exceeded", f"{overrides['simulations']} training simulations is over the "
                           f"server's limit of {config.max_train_simulations}", 422)
    try:
        steps = overrides.get("steps") or scene.simulation.steps
    except (OverflowError, ValueError):  # duration / dt beyond any integer (e.g. 1e308 / 0.01)
        sim = scene.simulation
        raise ServiceError("limit_exceeded", f"the scene's duration {sim.duration:g} s in steps of "
                           f"{sim.dt:g} s is beyond counting, over the server's limit of {config.max_steps} "
                           f"integration substeps", 422) from None
    try:
        substeps = int(scene.simulation.extra.get("substeps", default_substeps(scene)))
    except ValueError:
        substeps = default_substeps(scene)  # the simulator reports it when it builds the world
    if steps * max(substeps, 1) > config.max_steps:
        def n(x):
            return f"{x}" if x < 10 ** 12 else f"{float(x):.3g}"

        raise ServiceError("limit_exceeded", f"the rollout has {n(steps * substeps)} integration substeps "
                           f"({n(steps)} steps x {substeps} substeps), over the server's limit of "
                           f"{config.max_steps}", 422)
    if kind in ("solve", "heatmap"):
        iterations = overrides.get("iterations") or inf.iterations
        if iterations > config.max_iterations:
            raise ServiceError("limit_exceeded", f"{iterations} iterations is over the server's limit "
                               f"of {config.max_iterations}", 422)
    if kind == "heatmap":
        from dejaview.scene.model import HeatmapSettings

        settings = inf.heatmap or HeatmapSettings()
        nx, ny = overrides.get("cells") or settings.cells
        samples = overrides.get("samples") or settings.samples
        if nx * ny * samples > config.max_heatmap_runs:
            raise ServiceError("limit_exceeded", f"a heatmap of {nx} x {ny} cells with {samples} samples "
                               f"each is {nx * ny * samples} runs, over the server's limit of "
                               f"{config.max_heatmap_runs}", 422)
