"""Mesh file names in robot files (URDF, MJCF): paths relative to the file, absolute paths, ``file://``
URIs, and ``package://NAME/path`` URIs by the scene format's search path (spec: "Robots as users have
them").

The search path: the robot file's own folder and the folders above it, then the folders of
``DEJAVIEW_PACKAGE_PATH`` and ``ROS_PACKAGE_PATH``; the service confines the search to its scene root.
"""

from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import unquote, urlsplit

__all__ = ["PACKAGE_PATH_VARIABLES", "resolve_mesh", "resolve_package"]

PACKAGE_PATH_VARIABLES = ("DEJAVIEW_PACKAGE_PATH", "ROS_PACKAGE_PATH")
"""Environment variables whose folders (``os.pathsep``-separated) ``package://`` URIs are looked for in,
in this order, after the robot file's folder and the folders above it."""


def resolve_package(uri: str, robot_file: Path, root: Path | None = None) -> Path:
    """The file a ``package://NAME/path`` URI names, by the scene format's search path.

    Looked for, in this order, in the robot file's folder and each folder above it, then in the
    folders of ``DEJAVIEW_PACKAGE_PATH`` and ``ROS_PACKAGE_PATH`` (``PACKAGE_PATH_VARIABLES``;
    ``dejaview --package-path`` puts its folders first in ``DEJAVIEW_PACKAGE_PATH``): in a folder F,
    ``F/path`` where F is called NAME, else ``F/NAME/path`` (the URI's path as it stands). With
    ``root``, only folders inside it are searched and only files inside it (symlinks resolved) found.

    Args:
        uri: ``package://NAME/path``.
        robot_file: the URDF or MJCF file naming it.
        root: the folder the search is confined to, or None.
    Returns:
        The file's path (absolute).
    Raises:
        ValueError: a URI without a NAME or a path, or one found nowhere: one line listing where it
            looked.
    """
    name, _, rest = uri[len("package://"):].partition("/")
    if not name or not rest or name in (".", ".."):
        raise ValueError("a package:// URI needs a package name and a path: package://NAME/path")
    real_root = None if root is None else Path(os.path.realpath(root))

    def usable(folder: Path) -> bool:
        return real_root is None or Path(os.path.realpath(folder)).is_relative_to(real_root)

    start = Path(os.path.abspath(robot_file)).parent
    upward = [f for f in (start, *start.parents) if usable(f)]
    listed = []
    for variable in PACKAGE_PATH_VARIABLES:
        folders = [Path(os.path.abspath(f)) for f in os.environ.get(variable, "").split(os.pathsep) if f]
        listed.append((variable, [f for f in folders if usable(f)]))
    for folder in upward + [f for _, folders in listed for f in folders]:
        candidates = ([folder / rest] if folder.name == name else []) + [folder / name / rest]
        for candidate in candidates:
            if candidate.is_file() and usable(candidate):
                return candidate
    searched = f"{upward[0]} and the {len(upward) - 1} folders above it" if upward else "no folder"
    variables = "; ".join(f"{v}: {os.pathsep.join(map(str, fs)) if fs else '(none)'}" for v, fs in listed)
    inside = " inside the scene root" if root is not None else ""
    raise ValueError(f"package {name!r} not found: looked for {name}/{rest}{inside} in {searched}; {variables} "
                     "(add the folder that holds the package with --package-path or DEJAVIEW_PACKAGE_PATH)")


def resolve_mesh(name: str, robot_file: Path, base: Path | None = None, root: Path | None = None) -> Path:
    """The file a robot file's mesh name stands for: one rule for URDF and MJCF.

    ``package://NAME/path``: :func:`resolve_package`; ``file:///abs/path`` (or ``file://localhost/...``):
    that absolute path, percent-escapes decoded; an absolute path as it stands; a relative path
    against ``base`` (an MJCF model's ``meshdir``), else the robot file's folder. Whether the file
    exists is the caller's question, except for ``package://`` (found on the search path or not).

    Args:
        name: the name as the robot file writes it.
        robot_file: the URDF or MJCF file.
        base: the folder relative names resolve against (default: the robot file's folder).
        root: where given, ``package://`` URIs are searched for only inside it.
    Returns:
        The file's path (absolute).
    Raises:
        ValueError: a URI other than ``package://`` and ``file://``, a ``file://`` URI that names
            no absolute local path, or a package found nowhere: one line saying what was looked for
            and where.
    """
    if name.startswith("package://"):
        return resolve_package(name, robot_file, root)
    if name.startswith("file:"):
        uri = urlsplit(name)
        if uri.netloc not in ("", "localhost") or not uri.path.startswith("/") or uri.query or uri.fragment:
            raise ValueError("a file:// URI names an absolute path on this machine: file:///abs/path "
                             "(else give a path relative to the robot file, or package://NAME/path)")
        return Path(unquote(uri.path))
    if "://" in name:
        raise ValueError(f"{name.partition('://')[0]}:// URIs are not resolved: give a path relative to the "
                         "robot file, an absolute path, file:///abs/path or package://NAME/path")
    path = Path(name)  # joined, not normalised: ".." after a symlinked folder means what the OS says
    return path if path.is_absolute() else Path(base if base is not None else Path(robot_file).parent).absolute() / path
