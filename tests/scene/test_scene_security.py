"""The reader never expands entities, fetches anything or reads past its size limit."""

from __future__ import annotations

import socket
import tracemalloc
from pathlib import Path

import pytest
from lxml import etree

from dejaview.errors import SceneError
from dejaview.scene import Scene
from dejaview.untrusted_xml import hardened_parser
from dejaview.scene.xml import DEFAULT_MAX_BYTES, read_scene_file, read_scene_string

BROKEN = Path(__file__).resolve().parents[1] / "fixtures" / "scenes" / "broken"


@pytest.fixture
def no_network(monkeypatch):
    """Make any attempt to open a socket fail the test."""
    def refuse(*args, **kwargs):
        raise AssertionError("the scene reader tried to open a network connection")
    monkeypatch.setattr(socket, "socket", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


@pytest.fixture
def never_parsed(monkeypatch):
    """The XML parser must not be reached: a bomb is refused by the byte scan before it."""
    def refuse(*args, **kwargs):
        raise AssertionError("the document reached the XML parser")

    monkeypatch.setattr(etree, "fromstring", refuse)


def test_billion_laughs_is_refused_before_parsing_and_small(never_parsed):
    data = (BROKEN / "billion-laughs.xml").read_bytes()
    tracemalloc.start()
    try:
        with pytest.raises(SceneError) as info:
            read_scene_string(data, filename="bomb.xml")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "DOCTYPE declarations are not allowed" in str(info.value)
    assert "lol" not in str(info.value)
    assert peak < 2 * 1024 * 1024  # 10**9 "lol"s would be gigabytes


def test_bigger_bomb_in_a_file_is_refused(tmp_path, never_parsed):
    levels = ['<!ENTITY a0 "' + "x" * 1000 + '">']
    levels += [f'<!ENTITY a{i} "' + f"&a{i - 1};" * 16 + '">' for i in range(1, 12)]
    path = tmp_path / "bomb.xml"
    path.write_text('<?xml version="1.0"?>\n<!DOCTYPE scene [\n' + "\n".join(levels)
                    + ']>\n<scene version="1" name="&a11;"/>\n')
    with pytest.raises(SceneError) as info:
        read_scene_file(path)
    assert info.value.line == 2 and info.value.element == "!DOCTYPE"


def test_external_file_entity_is_never_read(tmp_path, no_network):
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET-MARKER")
    doc = (f'<?xml version="1.0"?>\n<!DOCTYPE scene [<!ENTITY s SYSTEM "{secret.as_uri()}">]>\n'
           '<scene version="1" name="&s;"><object id="b" shape="sphere" radius="1">'
           '<pose position="0 0 0"/></object></scene>')
    with pytest.raises(SceneError) as info:
        read_scene_string(doc)
    assert "TOP-SECRET-MARKER" not in str(info.value)
    with pytest.raises(SceneError):
        Scene.from_xml(BROKEN / "external-entity-file.xml")


def test_parser_itself_resolves_no_external_entity(tmp_path):
    """Defence in depth: even past the DOCTYPE refusal, the parser would not read the file."""
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET-MARKER")
    doc = (f'<!DOCTYPE s [<!ENTITY s SYSTEM "{secret.as_uri()}">]><s>&s;</s>').encode()
    root = etree.fromstring(doc, hardened_parser())
    assert b"TOP-SECRET-MARKER" not in etree.tostring(root)


@pytest.mark.parametrize("name", ["external-entity-http.xml", "external-dtd.xml"])
def test_network_entities_and_dtds_are_not_fetched(name, no_network):
    with pytest.raises(SceneError, match="DOCTYPE declarations are not allowed"):
        Scene.from_xml(BROKEN / name)


@pytest.mark.parametrize("decl", [
    '<!DOCTYPE scene>',
    '<!DOCTYPE scene PUBLIC "-//x//y" "scene.dtd">',
    '<!-- c -->\n<!DOCTYPE scene [ ]>',
])
def test_any_doctype_is_refused(decl):
    doc = f'<?xml version="1.0"?>\n{decl}\n<scene version="1"/>'
    with pytest.raises(SceneError, match="DOCTYPE declarations are not allowed"):
        read_scene_string(doc)


def test_size_limit_on_strings():
    doc = '<scene version="1">' + " " * 2000 + "</scene>"
    with pytest.raises(SceneError) as info:
        read_scene_string(doc, max_bytes=1000)
    assert f"{len(doc)} bytes" in info.value.reason and "1000 bytes" in info.value.reason


def test_size_limit_on_files_is_checked_before_reading(tmp_path, monkeypatch):
    import dejaview.scene.xml as xml_module

    path = tmp_path / "huge.xml"
    with open(path, "wb") as fh:
        fh.truncate(50 * DEFAULT_MAX_BYTES)  # sparse: costs no disk
    read = []

    class Counting:
        """The reader's file, counting the bytes it reads."""

        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

        def fileno(self):
            return self.fh.fileno()

        def read(self, n=-1):
            data = self.fh.read(n)
            read.append(len(data))
            return data

    monkeypatch.setattr(xml_module, "open", lambda *a, **k: Counting(open(*a, **k)), raising=False)
    with pytest.raises(SceneError) as info:
        read_scene_file(path)
    assert sum(read) <= DEFAULT_MAX_BYTES + 1  # at most the limit and one byte, never the file
    assert f"{50 * DEFAULT_MAX_BYTES} bytes" in info.value.reason
    assert "1 MiB" in info.value.reason
    assert info.value.file == str(path)


def test_default_limit_accepts_ordinary_scenes_with_padding():
    doc = ('<scene version="1"><!--' + "x" * (DEFAULT_MAX_BYTES // 2) + '-->'
           '<object id="b" shape="sphere" radius="1"><pose position="0 0 0"/></object></scene>')
    assert len(read_scene_string(doc).objects) == 1


def test_xinclude_is_not_processed():
    with pytest.raises(SceneError, match="unknown element"):
        Scene.from_xml(BROKEN / "xinclude.xml")


def test_deep_nesting_is_refused_cleanly():
    doc = '<scene version="1">' + "<object>" * 100000 + "</object>" * 100000 + "</scene>"
    with pytest.raises(SceneError):
        read_scene_string(doc)
