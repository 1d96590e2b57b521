"""An MJCF model and the files it names, read as the scene format reads robot files, and compiled by
MuJoCo from memory: shared by ``<object mjcf=...>`` (``dejaview.geometry.robot``) and
``dejaview import-mjcf`` (``dejaview.io.mjcf``).

* ``<include file>`` is spliced in (its ``<mujoco>``'s children in its place, as MuJoCo does), each
  file read as untrusted XML (``dejaview.untrusted_xml``);
* ``<mesh file>`` names resolve by the robot files' one rule (``dejaview.geometry.packages.
  resolve_mesh``: relative to ``<compiler meshdir>`` or ``assetdir``, else to the model's folder;
  absolute; ``file://``; ``package://``), ``strippath`` honoured; the bytes are handed to MuJoCo
  as in-memory assets, so MuJoCo itself opens no file;
* textures read from files and skins are left out (drawing only), and materials' references to them.

With ``root`` (the service's scene root) every file must lie inside it, symlinks resolved.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

from dejaview.errors import SceneError

__all__ = ["MJCF_MESH_SUFFIXES", "MJCFSource", "MeshOutsideRoot", "compile_mjcf", "read_mjcf"]

MAX_MJCF_BYTES = 4 << 20
"""Largest MJCF file (each included file too) read: 4 MiB."""
MAX_MESH_BYTES = 256 << 20
"""Largest mesh file handed to MuJoCo: 256 MiB."""
MAX_INCLUDE_DEPTH = 8
MJCF_MESH_SUFFIXES = (".obj", ".stl")
"""Mesh files both MuJoCo and DejaView (``dejaview.geometry.MESH_SUFFIXES``) read."""


class MeshOutsideRoot(SceneError):
    """A file an MJCF model names that lies outside the scene root (the service refuses it unread)."""


@dataclass(frozen=True)
class MJCFSource:
    """An MJCF model ready for MuJoCo.

    Attributes:
        path: the model file.
        text: the model as one document: includes spliced, mesh files renamed to asset keys,
            ``meshdir``/``assetdir``/``strippath`` dropped, file textures and skins left out.
        assets: (key, file) of each mesh file, in the order named.
        meshes: (mesh name, file) of each mesh asset read from a file.
        files: every file read besides ``path`` (included files, meshes).
    """

    path: Path
    text: bytes
    assets: tuple[tuple[str, Path], ...] = ()
    meshes: tuple[tuple[str, Path], ...] = ()
    files: tuple[Path, ...] = ()


def _err(path: Path, el, reason: str, cls=SceneError) -> SceneError:
    return cls(reason, str(path), getattr(el, "sourceline", None), getattr(el, "tag", None))


def _inside(path: Path, root: Path | None) -> bool:
    return root is None or Path(os.path.realpath(path)).is_relative_to(Path(os.path.realpath(root)))


def _parse(path: Path, root: Path | None, el=None, parent: Path | None = None):
    from dejaview.untrusted_xml import parse_xml

    if parent is not None and not _inside(path, root):
        raise _err(parent, el, f"<include file={el.get('file')!r}> leads outside the scene root", MeshOutsideRoot)
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_MJCF_BYTES + 1)
    except OSError as exc:
        if parent is None:
            raise SceneError(f"cannot read MJCF file: {exc.strerror or exc}", str(path)) from None
        raise _err(parent, el, f"<include file={el.get('file')!r}>: cannot read {path}: {exc.strerror or exc}") from None
    if len(data) > MAX_MJCF_BYTES:
        raise SceneError(f"MJCF file is over the {MAX_MJCF_BYTES >> 20} MiB limit", str(path))
    tree = parse_xml(data, filename=str(path), max_bytes=MAX_MJCF_BYTES, what="MJCF files")
    if tree.tag != "mujoco":
        raise _err(path, tree, f"the root element is <{tree.tag}>, an MJCF model's is <mujoco>")
    return tree


def read_mjcf(path: str | Path, root: Path | None = None) -> MJCFSource:
    """Read an MJCF model and the files it names (module docstring).

    Args:
        path: the model file.
        root: where given, every file must lie inside this folder (symlinks resolved).
    Raises:
        MeshOutsideRoot: with ``root``, a file that lies outside it (not read).
        SceneError: naming the file, line and element: unreadable or hostile XML, an include
            deeper than ``MAX_INCLUDE_DEPTH``, a mesh file not found (saying where it was looked
            for) or of a suffix MuJoCo and DejaView do not both read, a height field from a file.
    """
    from lxml import etree

    from dejaview.geometry.packages import resolve_mesh

    path = Path(path)
    tree = _parse(path, root)
    files = []
    for depth in range(MAX_INCLUDE_DEPTH + 1):
        includes = [el for el in tree.iter("include")]
        if not includes:
            break
        if depth == MAX_INCLUDE_DEPTH:
            raise _err(path, includes[0], f"includes nested over {MAX_INCLUDE_DEPTH} deep")
        for el in includes:
            name = el.get("file")
            if not name:
                raise _err(path, el, "an <include> needs a 'file'")
            if "://" in name:
                raise _err(path, el, f"<include file={name!r}>: give a path relative to the model file")
            file = Path(name) if Path(name).is_absolute() else path.absolute().parent / name
            sub = _parse(file, root, el, path)
            files.append(file)
            parent, at = el.getparent(), el.getparent().index(el)
            parent.remove(el)
            for k, child in enumerate(list(sub)):
                parent.insert(at + k, child)
    meshdir = assetdir = None
    strip = False
    for compiler in tree.iter("compiler"):
        meshdir = compiler.get("meshdir", meshdir)
        assetdir = compiler.get("assetdir", assetdir)
        strip = compiler.get("strippath", "true" if strip else "false") == "true"
        for attr in ("meshdir", "assetdir", "texturedir", "strippath"):
            compiler.attrib.pop(attr, None)
    folder = meshdir if meshdir is not None else assetdir
    base = path.absolute().parent / folder if folder else None
    where = f" ({'meshdir' if meshdir is not None else 'assetdir'} {folder!r})" if folder else ""
    dropped = set()
    for el in list(tree.iter("texture", "skin", "hfield")):
        if el.tag == "hfield" and el.get("file") is not None:
            raise _err(path, el, "a height field from a file is not supported (nor are height field geoms)")
        if any(k.startswith("file") for k in el.attrib):  # drawing only: never opened
            dropped.add(el.get("name") or Path(el.get("file", "")).stem)
            el.getparent().remove(el)
    for el in tree.iter("material"):
        if el.get("texture") in dropped:
            el.attrib.pop("texture")
        for layer in list(el.iter("layer")):
            if layer.get("texture") in dropped:
                el.remove(layer)
    assets, meshes = [], []
    for el in tree.iter("mesh"):
        name = el.get("file")
        if name is None or el.getparent() is None or el.getparent().tag != "asset":
            continue
        shown = Path(name).name if strip and "://" not in name else name
        try:
            file = resolve_mesh(shown, path, base=base, root=root)
        except ValueError as exc:
            raise _err(path, el, f"mesh {name!r}: {exc}") from None
        suffix = file.suffix.lower()
        if suffix not in MJCF_MESH_SUFFIXES:
            raise _err(path, el, f"mesh {name!r}: unsupported suffix {suffix or '(none)'!r} (use one of "
                                 f"{', '.join(MJCF_MESH_SUFFIXES)})")
        if not _inside(file, root):
            raise _err(path, el, f"mesh {name!r} leads outside the scene root", MeshOutsideRoot)
        if not file.is_file():
            raise _err(path, el, f"mesh {name!r}: file not found: looked for {file}{where}")
        if file.stat().st_size > MAX_MESH_BYTES:
            raise _err(path, el, f"mesh {name!r}: {file} is over the {MAX_MESH_BYTES >> 20} MiB limit")
        key = f"dejaview-mesh-{len(assets)}{suffix}"
        mesh_name = el.get("name") or Path(shown).stem  # MuJoCo's default name: the file's, stripped
        el.set("name", mesh_name)
        el.set("file", key)
        assets.append((key, file))
        meshes.append((mesh_name, file))
        files.append(file)
    return MJCFSource(path=path, text=etree.tostring(tree), assets=tuple(assets), meshes=tuple(meshes),
                      files=tuple(files))


def compile_mjcf(source: MJCFSource):
    """MuJoCo's model of ``source`` (kept for the process while its files stay as they are).

    Raises:
        SceneError: no mujoco package, or MuJoCo cannot compile the model (its message, one line).
    """
    stamps = []
    for _, file in source.assets:
        st = file.stat()
        stamps.append((str(file), st.st_mtime_ns, st.st_size))
    return _compiled(source.text, tuple(k for k, _ in source.assets), tuple(stamps), str(source.path))


@functools.lru_cache(maxsize=16)
def _compiled(text: bytes, keys: tuple, stamps: tuple, where: str):
    try:
        import mujoco
    except ImportError:
        raise SceneError("MJCF models need the mujoco package: pip install mujoco", where) from None
    assets = {}
    for key, (file, _, _) in zip(keys, stamps):
        with open(file, "rb") as fh:
            assets[key] = fh.read(MAX_MESH_BYTES + 1)
    try:
        return mujoco.MjModel.from_xml_string(text.decode("utf-8"), assets=assets)
    except (ValueError, UnicodeDecodeError) as exc:
        raise SceneError(f"MuJoCo cannot compile the model: {' '.join(str(exc).split())}", where) from None
