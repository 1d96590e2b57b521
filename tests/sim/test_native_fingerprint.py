"""Today's native engine against a record of it (states and both gradients, to 1e-9).

Issue 25 rewrote how the engine differentiates (the adjoint instead of full state Jacobians,
then hand-written reverse mode) and how it culls contacts, under the contract that states and
gradients stay those of the engine it was filed against (30cf17f) to 1e-9; this test held it
there. The friction on the predicted slip (2026-11-25, ``dejaview.sim.contacts``) then changed
the physics of impacts on purpose, and the record (``scripts/native_fingerprint.py`` on the
bundled scenes: 150 steps, states every 10th, the reverse-mode gradient and a forward-mode
derivative of a loss of them) was of that engine; the roll stick of a line contact
(2026-11-26, ``dejaview.sim.line_contact``) changed the physics of bodies on an edge or a line
on purpose (of the bundled scenes the two mugs and the box among boxes; the others within 6e-17),
and the record was of that engine (``fingerprint-roll-stick.npz``, in the git history); the
loading-to-unloading blend over a part of an impact's phase (2026-12-07, ``restitution.loading``:
restitution no longer depends on where in its substep an impact's deepest point falls) changed
every scene with a contact in its 150 steps on purpose, and the record was of that engine
(``fingerprint-phase-blend.npz``, in the git history); the unloading factor below zero for
restitutions under 0.111, cut off where the force would pull (2026-12-07,
``restitution.UNLOAD_MIN``), changed the two bundled scenes at restitution 0.1 (box_along_shelf,
box_among_boxes; the others bit for bit) on purpose, and the record is now of that engine:
``tests/fixtures/native/fingerprint-unload-min.npz``. A change to the C++ that should not change
a number must keep this test passing; one that should must say why and re-record.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from dejaview.sim import native

ROOT = Path(__file__).resolve().parents[2]
BEFORE = ROOT / "tests" / "fixtures" / "native" / "fingerprint-unload-min.npz"
TOLERANCE = 1e-9  # times max(1, the largest magnitude of the array)

pytestmark = pytest.mark.skipif(not native.available(), reason="the native extension does not build here")


def _script():
    spec = importlib.util.spec_from_file_location("native_fingerprint", ROOT / "scripts" / "native_fingerprint.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_states_and_gradients_equal_the_recorded_engine(tmp_path):
    fingerprint = _script()
    after = tmp_path / "now.npz"
    fingerprint.record(after, ROOT / "examples" / "scenes")
    diffs = fingerprint.differences(BEFORE, after)
    before = np.load(BEFORE)
    compared = {k: d for k, d in diffs.items() if d is not None}
    assert len(compared) >= 12, diffs  # most scenes still as they were then (a changed scene file is skipped)
    kinds = {k.split("/")[1] for k in compared}
    assert kinds == {"states", "reverse", "forward"}
    for key, diff in compared.items():
        scale = max(1.0, float(np.abs(before[key]).max()))
        assert diff <= TOLERANCE * scale, (key, diff, scale)
