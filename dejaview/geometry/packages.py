"""``package://NAME/path`` URIs of robot files: the scene format's search path (spec: "Robots as users
have them").

The robot file's own folder and the folders above it, then the folders of ``DEJAVIEW_PACKAGE_PATH`` and
``ROS_PACKAGE_PATH``; the service confines the search to its scene root.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["PACKAGE_PATH_VARIABLES", "resolve_package"]

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
