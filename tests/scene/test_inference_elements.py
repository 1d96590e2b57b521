"""The one table of ``<inference>``'s children (``dejaview.scene.inference_elements``) says what
the schema says, and a scene with every element and attribute in it reads back as written."""

from dataclasses import fields
from pathlib import Path

from lxml import etree

from dejaview.scene.inference_elements import INFERENCE_ELEMENTS, KINDS
from dejaview.scene.xml import read_scene_string

XSD = Path(__file__).resolve().parents[2] / "dejaview" / "scene" / "scene.xsd"
NS = {"xs": "http://www.w3.org/2001/XMLSchema"}


def _schema_children_and_attributes() -> dict[str, set[str]]:
    tree = etree.parse(str(XSD))
    inference = tree.find(".//xs:complexType[@name='InferenceType']", NS)
    out = {}
    for el in inference.iterfind(".//xs:element", NS):
        kind = tree.find(f".//xs:complexType[@name='{el.get('type')}']", NS)
        out[el.get("name")] = {a.get("name") for a in kind.iterfind(".//xs:attribute", NS)}
    return out


def test_the_table_holds_the_schemas_elements_and_attributes():
    schema = _schema_children_and_attributes()
    assert {e.tag: {a.xml for a in e.attributes} for e in INFERENCE_ELEMENTS} == schema
    for e in INFERENCE_ELEMENTS:
        names = {f.name for f in fields(e.cls)}
        assert all(a.field in names and a.kind in KINDS for a in e.attributes), e.tag


def test_every_element_and_attribute_reads_back_as_written():
    text = """<scene version="1" name="all" gravity="0 0 -9.81">
  <simulation dt="0.01" duration="1.0" friction="0.5" restitution="0.2"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.4"><pose position="0 0 0.5" orientation="1 0 0 0"/></object>
  <inference source="ball" optimizer="auto" seed="3">
    <target position="0.1 0 0.05" orientation="1 0 0 0" time="0.5" moving="true"
            linear-velocity="1 0 0" angular-velocity="0 1 0"/>
    <target position="0.2 0 0.05"/>
    <optimize position="true" orientation="false" linear-velocity="true" angular-velocity="true"/>
    <start-area min="-0.5 -0.5 0.5" max="0.5 0.5 0.5"/>
    <exploration epsilon="0.3" patience="7"/>
    <penalty between="ball floor" weight="2.0"/>
    <heatmap cells="4 3" samples="2" sigma="0.03"/>
    <prior speed="1.0" spin="3.0" tilt="0.05"/>
    <observation sigma="0.004" angle-sigma="0.06" rest-speed="0.03" rest-spin="0.3"/>
    <model-uncertainty friction="0.1" restitution="0.2"/>
    <posterior samples="12"/>
  </inference>
</scene>"""
    scene = read_scene_string(text)
    inf = scene.inference
    assert (len(inf.targets), inf.targets[0].moving, inf.targets[1].orientation) == (2, True, None)
    assert (inf.optimize.orientation, inf.exploration.patience, inf.penalties[0].between) == (False, 7, ("ball", "floor"))
    assert (inf.heatmap.cells, inf.prior.tilt, inf.observation.rest_spin) == ((4, 3), 0.05, 0.3)
    assert (inf.model_uncertainty.restitution, inf.posterior.samples) == (0.2, 12)
    again = read_scene_string(scene.to_xml())
    assert again == scene
