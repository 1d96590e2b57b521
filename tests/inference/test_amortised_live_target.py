"""``observables.with_target``: a new target written into a cached observation vector is the
observation vector of the scene with that target (position, orientation, rest window alike)."""

from __future__ import annotations

import torch

from dejaview.inference.amortised.observables import observed, with_target
from dejaview.inference.posterior import Posterior
from dejaview.scene import Scene

BOX = """<scene version="1" name="box-seen-twice">
  <simulation dt="0.01" duration="0.5" friction="0.5" restitution="0.1"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="box" shape="box" size="0.1 0.1 0.1" mass="0.5"><pose position="0 0 0.3"/></object>
  <inference source="box" loss="pose" evaluate="final" seed="0">
    <target position="0.05 0.0 0.2" time="0.2" moving="true"/>
    <target {seen}/>
    <start-area min="-0.1 -0.1 0.3" max="0.1 0.1 0.3"/>
  </inference>
</scene>
"""
SEEN = 'position="0.3 0.1 0.05" orientation="1 0 0 0"'


def test_new_target_in_the_cached_vector_is_the_moved_scenes_own_vector():
    """The anchor (the untimed, lying-still sighting) is replaced, not the timed one before it."""
    post = Posterior.from_scene(Scene.from_string(BOX.format(seen=SEEN)))
    assert len(post.sightings) == 2 and post.sightings[1].at_rest
    position, orientation = [0.25, -0.1, 0.05], [0.5, 0.5, -0.5, 0.5]
    moved = Scene.from_string(BOX.format(seen='position="0.25 -0.1 0.05" orientation="0.5 0.5 -0.5 0.5"'))
    want = observed(Posterior.from_scene(moved))
    y = observed(post)
    got = with_target(post, y, position, [2 * v for v in orientation])  # a quaternion of any length
    assert got.shape == y.shape and torch.allclose(got, want, atol=1e-12)
    assert not torch.equal(got, y) and torch.equal(y, observed(post))  # the cached vector is left alone
    same = with_target(post, y, position, None)  # no orientation given: the scene's is kept
    k = 3  # the timed sighting: its position (it gives no orientation)
    assert torch.equal(got[:k], y[:k])
    assert torch.allclose(same[k:k + 3], want[k:k + 3]) and torch.equal(same[k + 3:], y[k + 3:])
