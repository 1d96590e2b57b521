"""Physical bounds and the step budget where a scene is read (``dejaview.scene.bounds``): what
``dejaview simulate`` would refuse, ``dejaview validate`` says first, with the element and line."""

from __future__ import annotations

import pytest

from dejaview.errors import DejaViewError, SceneError
from dejaview.scene import bounds
from dejaview.scene.xml import read_scene_string

SCENE = """<?xml version="1.0"?>
<scene version="1" gravity="{gravity}">
  <simulation dt="{dt}" duration="{duration}" friction="{friction}" restitution="0.2"{extra}/>
  <object id="floor" shape="plane" fixed="true">
    <pose position="0 0 0"/>
  </object>
  <object id="box" shape="box" size="{size}"{material}>
    <pose position="{position}"/>
    <velocity linear="{linear}" angular="{angular}"/>
  </object>
</scene>
"""
GOOD = dict(gravity="0 0 -9.81", dt="0.002", duration="1", friction="0.5", extra="", size="0.1 0.1 0.1",
            material=' mass="1"', position="0 0 0.5", linear="1 0 0", angular="0 0 1")


def read(max_steps=None, **changes):
    return read_scene_string(SCENE.format(**{**GOOD, **changes}), max_steps=max_steps)


def test_the_good_scene_reads():
    assert read().object("box").mass == 1.0


@pytest.mark.parametrize("changes, line, element, fragment", [
    (dict(gravity="0 0 -1e300"), 2, "scene", "'gravity' has magnitude 1e+300 m/s^2, beyond the limit of 1000"),
    (dict(dt="2"), 3, "simulation", "'dt' 2.0 s is beyond the limit of 1 s"),
    (dict(friction="1e300"), 3, "simulation", "'friction' 1e+300 is beyond the limit of 10"),
    (dict(size="1e-300 1 1"), 7, "object", "'size' 1e-300 m is below the smallest meaningful value, 0.0001 m"),
    (dict(size="1e5 1 1"), 7, "object", "'size' 100000.0 m is beyond the limit of 10000 m"),
    (dict(material=' mass="1e300"'), 7, "object", "'mass' 1e+300 kg is beyond the limit of 1e+09 kg"),
    (dict(material=' mass="1e-300"'), 7, "object", "'mass' 1e-300 kg is below the smallest"),
    (dict(material=' density="1e8"'), 7, "object", "'density' 100000000.0 kg/m^3 is beyond the limit"),
    (dict(material=' density="1e6"', size="10 10 10.1"), 7, "object",  # the density is in range, not the mass
     "object 'box' would weigh 1.01e+09 kg (density x volume)"),
    (dict(position="1e300 0 0"), 8, "pose", "'position' 1e+300 m is beyond the limit of 10000 m"),
    (dict(linear="1e200 0 0"), 9, "velocity", "'linear' has magnitude 1e+200 m/s, beyond the limit of 10000"),
    (dict(angular="0 7e3 8e3"), 9, "velocity", "'angular' has magnitude 1.063e+04 rad/s, beyond the limit"),
    (dict(extra=' substeps="0"'), 3, "simulation", "substeps='0' must be at least 1"),
    (dict(extra=' substeps="1e9"'), 3, "simulation", "substeps='1e9' is not an integer"),
    (dict(extra=' substeps="1001"'), 3, "simulation", "substeps='1001' is over the limit of 1000"),
    (dict(extra=' unload-velocity="-1"'), 3, "simulation", "unload-velocity='-1' must be positive"),
    (dict(extra=' unload-velocity="nan"'), 3, "simulation", "unload-velocity='nan' is not finite"),
    (dict(extra=' sdf-spacing="1e-9"'), 3, "simulation", "sdf-spacing='1e-9' must be at least 0.0001"),
    (dict(extra=' max-pair-contacts="99999999999999999999"'), 3, "simulation", "is over the limit of 1e+09"),
    (dict(extra=' contact-frequency="1e300"'), 3, "simulation",
     "contact-frequency='1e300' is unstable with substeps of 0.0005 s"),  # a box body: 4 substeps
    (dict(extra=' substeps="4" contact-frequency="4001"'), 3, "simulation", "unstable with substeps of 0.0005 s"),
    (dict(dt="1e-300"), 3, "simulation", "1.0 s / 1e-300 s is 1e+300 steps x 4 substeps = 4e+300 integration"),
    (dict(duration="1e308"), 3, "simulation", "over the budget of 2000000"),
    (dict(dt="0.001", duration="2000.001", extra=' substeps="1"'), 3, "simulation",
     "2000.001 s / 0.001 s is 2000001 steps = 2000001 integration steps, over the budget of 2000000"),
])
def test_what_is_refused_and_where(changes, line, element, fragment):
    with pytest.raises(SceneError) as err:
        read(**changes)
    e = err.value
    assert (e.line, e.element) == (line, element) and fragment in e.reason, str(e)
    assert "\n" not in str(e)


def test_at_the_limits_is_accepted():
    read(gravity="0 0 -1000", dt="1", duration="1", friction="10", size="1e-4 1e4 1",
         material=' mass="1e9"', position="1e4 -1e4 0", linear="1e4 0 0", angular="0 0 1e4",
         extra=' substeps="1000" contact-frequency="2000" unload-velocity="1e4" sdf-spacing="1e-4"')
    read(dt="0.001", duration="1000", extra=' substeps="2"')  # exactly 2,000,000 integration steps


def test_the_step_budget_can_be_raised(monkeypatch):
    with pytest.raises(SceneError, match="over the budget of 2000000"):
        read(dt="1e-6", duration="2")
    # 2,000,000 steps of the box body's 4 substeps (bounds.BOX_BODY_SUBSTEPS)
    assert read(max_steps=8_000_000, dt="1e-6", duration="2").simulation.steps == 2_000_000
    monkeypatch.setenv("DEJAVIEW_MAX_STEPS", "8000000")
    assert read(dt="1e-6", duration="2").simulation.steps == 2_000_000
    with pytest.raises(SceneError, match="over the budget of 10 "):
        read(max_steps=10)
    monkeypatch.setenv("DEJAVIEW_MAX_STEPS", "lots")
    with pytest.raises(DejaViewError, match="DEJAVIEW_MAX_STEPS must be a positive integer, got 'lots'"):
        read()


def test_steps_never_overflow():
    scene = read()
    huge = scene.replace(simulation=scene.simulation.__class__(dt=1e-300, duration=1e308))
    assert huge.simulation.steps > bounds.MAX_STEPS
