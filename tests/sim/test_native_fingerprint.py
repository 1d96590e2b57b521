"""Today's native engine against the one issue 25 was filed against (commit 30cf17f).

Issue 25 rewrote how the engine differentiates (the adjoint instead of full state Jacobians,
then hand-written reverse mode) and how it culls contacts; its contract is that states and
gradients stay those of the engine before, to 1e-9. ``scripts/native_fingerprint.py`` recorded
that engine on the bundled scenes (``tests/fixtures/native/fingerprint-30cf17f.npz``: 150
steps, states every 10th, the reverse-mode gradient and a forward-mode derivative of a loss of
them); here today's engine records the same and must match.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from dejaview.sim import native

ROOT = Path(__file__).resolve().parents[2]
BEFORE = ROOT / "tests" / "fixtures" / "native" / "fingerprint-30cf17f.npz"
TOLERANCE = 1e-9  # times max(1, the largest magnitude of the array)

pytestmark = pytest.mark.skipif(not native.available(), reason="the native extension does not build here")


def _script():
    spec = importlib.util.spec_from_file_location("native_fingerprint", ROOT / "scripts" / "native_fingerprint.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_states_and_gradients_equal_the_engine_issue_25_was_filed_against(tmp_path):
    fingerprint = _script()
    after = tmp_path / "now.npz"
    fingerprint.record(after, ROOT / "examples" / "scenes")
    diffs = fingerprint.differences(BEFORE, after)
    before = np.load(BEFORE)
    compared = {k: d for k, d in diffs.items() if d is not None}
    assert len(compared) >= 12, diffs  # most scenes still as they were then
    kinds = {k.split("/")[1] for k in compared}
    assert kinds == {"states", "reverse", "forward"}
    for key, diff in compared.items():
        scale = max(1.0, float(np.abs(before[key]).max()))
        assert diff <= TOLERANCE * scale, (key, diff, scale)
