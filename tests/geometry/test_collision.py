"""Exact interpenetration tests (dejaview.geometry.collision) against closed forms and the bundled scenes."""

from __future__ import annotations

import math
from pathlib import Path

import fcl
import numpy as np
import pytest
import torch
import trimesh

from dejaview.errors import GeometryError
from dejaview.geometry.collision import DEFAULT_MARGIN, TOUCHING, SceneCollision
from dejaview.geometry.transforms import quat_to_matrix
from dejaview.geometry.convex_pieces import convex_pieces, load_or_build_pieces
from dejaview.scene import Scene

ROOT = Path(__file__).resolve().parents[2]
SCENES = sorted((ROOT / "examples" / "scenes").glob("*.xml"))
MESHES = ROOT / "examples" / "meshes"
UP = (1.0, 0.0, 0.0, 0.0)


def scene_of(objects: str, base_dir=MESHES) -> Scene:
    """A scene from ``<object>`` elements (mesh names relative to examples/meshes)."""
    return Scene.from_string(f'<scene version="1">{objects}</scene>', base_dir=base_dir)


def obj(oid: str, geometry: str, position=(0, 0, 0), orientation=UP, fixed=False) -> str:
    return (f'<object id="{oid}" {geometry} fixed="{str(fixed).lower()}">'
            f'<pose position="{" ".join(map(str, position))}" '
            f'orientation="{" ".join(map(str, orientation))}"/></object>')


FLOOR = obj("floor", 'shape="plane"', fixed=True)


@pytest.fixture(scope="module")
def mug_counter() -> SceneCollision:
    return SceneCollision(Scene.from_xml(ROOT / "examples" / "scenes" / "mug_off_counter.xml"))


@pytest.fixture(scope="module")
def mug_body():
    """The bundled mug's mesh, for closed-form positions: bottom at z = -0.05, body axis at
    x = -0.014 (the handle on +x reaches 0.054), wall and bottom 12 mm."""
    from dejaview.geometry.mesh import load_mesh

    return load_mesh(MESHES / "mug.obj")


# ----------------------------------------------------------- bundled scenes
@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_bundled_scenes_have_no_interpenetration(path):
    """Every example starts with its objects resting or apart: nothing overlaps, not even by 1 um."""
    assert SceneCollision(Scene.from_xml(path)).interpenetrations(margin=0.0) == []


def test_mug_on_the_counter_is_feasible_and_5cm_down_is_not(mug_counter):
    """mug_off_counter: the mug stands on the counter top (z = 0.9) at its given pose."""
    hit, depth, other = mug_counter.penetration("mug", np.array([0.0, 0.0, 0.95]), np.array(UP))
    assert not hit[0] and depth[0] == 0.0 and other == [None]
    hit, depth, other = mug_counter.penetration("mug", np.array([[0.0, 0.0, 0.90]]), np.array([UP]))
    assert hit[0] and other == ["counter"]
    assert depth[0] == pytest.approx(0.05, abs=1e-4)


def test_mug_buried_inside_the_counter_is_found(mug_counter):
    """Entirely inside the counter no surfaces cross; it is a penetration all the same."""
    hit, depth, other = mug_counter.penetration("mug", np.array([0.0, 0.0, 0.5]), np.array(UP))
    assert hit[0] and other == ["counter"]
    # fcl's EPA is approximate this deep (the true minimum translation is 0.34 m, sideways)
    assert depth[0] > 0.3


def test_mug_below_the_floor_is_found(mug_counter):
    """The floor plane is a half-space: a mug under it, or half under it, penetrates it."""
    hit, depth, other = mug_counter.penetration(
        "mug", np.array([[2.0, 0.0, -0.5], [2.0, 0.0, 0.04], [2.0, 0.0, 0.05]]), np.array(UP))
    assert hit.tolist() == [True, True, False]
    assert other[:2] == ["floor", "floor"] and other[2] is None
    np.testing.assert_allclose(depth, [0.55, 0.01, 0.0], atol=1e-9)


def test_mug_over_the_counter_edge(mug_counter):
    """Moved 24 mm sideways into the counter's side (its bottom hangs below the top)."""
    # the mug's -x side is at x = -0.054: at x = 0.53 it reaches 0.476, 24 mm inside the edge at 0.5
    hit, depth, other = mug_counter.penetration("mug", np.array([0.53, 0.0, 0.9]), np.array(UP))
    assert hit[0] and other == ["counter"]
    assert depth[0] == pytest.approx(0.024, abs=2e-4)


def test_resting_contact_and_margin():
    """Touching is no penetration; a 0.5 mm overlap counts only without a margin over it."""
    c = SceneCollision(scene_of(FLOOR + obj("box", 'shape="box" size="0.2 0.2 0.1"', (0, 0, 0.05))))
    assert c.interpenetrations(margin=0.0) == []
    pos = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, 0.0495], [0.0, 0.0, 0.0495]])
    hit, depth, _ = c.penetration("box", pos, np.array(UP), margin=0.0)
    assert hit.tolist() == [False, True, True]
    np.testing.assert_allclose(depth, [0.0, 5e-4, 5e-4], atol=1e-12)
    hit, _, _ = c.penetration("box", pos, np.array(UP), margin=1e-3)
    assert not hit.any()


def test_box_inside_another_box():
    """A box wholly inside another: depth is the shortest way out (closed form), found both ways."""
    big = obj("big", 'shape="box" size="1 1 1"', (0, 0, 2), fixed=True)
    small = obj("small", 'shape="box" size="0.2 0.2 0.2"', (0.1, 0, 2))
    c = SceneCollision(scene_of(big + small))
    assert c.interpenetrations() == [("big", "small", pytest.approx(0.5))]
    # the same with meshes (both convex: fcl.Convex pieces)
    mesh_a = obj("a", 'mesh="box.obj"', (0, 0, 1))
    mesh_b = obj("b", 'mesh="box.obj"', (0.03, 0, 1))
    pairs = SceneCollision(scene_of(mesh_a + mesh_b)).interpenetrations()
    assert [(a, b) for a, b, _ in pairs] == [("a", "b")]
    assert pairs[0][2] == pytest.approx(0.1, abs=1e-9)  # out along z: both 10 cm tall, at one height


def test_fixed_pairs_are_skipped():
    """A table standing in the floor (two fixed objects) is not reported."""
    table = obj("table", 'mesh="table.obj"', (0, 0, -0.1), fixed=True)
    assert SceneCollision(scene_of(FLOOR + table)).interpenetrations() == []


def test_primitives_against_closed_forms():
    """Sphere into a box, a tilted cylinder and a box under a tilted plane."""
    tilt = math.radians(30)
    plane_q = (math.cos(tilt / 2), math.sin(tilt / 2), 0.0, 0.0)
    scene = scene_of(
        obj("slab", 'shape="box" size="1 1 0.2"', (0, 0, 0.1), fixed=True)
        + obj("ball", 'shape="sphere" radius="0.05"', (5, 0, 5))
        + obj("can", 'shape="cylinder" radius="0.05" height="0.2"', (7, 0, 5))
        + obj("tilted", 'shape="plane"', (10, 0, 0), plane_q, fixed=True))
    c = SceneCollision(scene)
    hit, depth, other = c.penetration("ball", np.array([0.0, 0.0, 0.23]), np.array(UP))
    assert hit[0] and other == ["slab"] and depth[0] == pytest.approx(0.02, abs=1e-6)
    # a cylinder lying on its side (axis x): its lowest line is r below its axis
    side = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)
    _, depth, _ = c.penetration("can", np.array([0.0, 0.0, 0.24]), np.array(side))
    assert depth[0] == pytest.approx(0.01, abs=1e-6)
    # under the tilted plane at x = 10 (normal (0, -sin 30, cos 30)): a ball at the plane's
    # origin, raised by h along the normal, reaches r - h below it
    normal = np.array([0.0, -math.sin(tilt), math.cos(tilt)])
    centre = np.array([10.0, 0.0, 0.0]) + 0.03 * normal
    hit, depth, other = c.penetration("ball", centre, np.array(UP))
    assert other == ["tilted"] and depth[0] == pytest.approx(0.02, abs=1e-12)
    _, depth, _ = c.penetration("can", np.array([10.0, 0.0, 0.0]) + 0.15 * normal,
                                np.array(plane_q))
    assert depth[0] == pytest.approx(0.0, abs=1e-12)  # standing on the plane, base 5 cm above it
    _, depth, _ = c.penetration("can", np.array([10.0, 0.0, 0.0]) + 0.08 * normal,
                                np.array(plane_q))
    assert depth[0] == pytest.approx(0.02, abs=1e-12)


def test_inner_balls_and_their_depths():
    """What the start-area check bounds a free orientation with (``dejaview.inference.start_area``):
    the largest ball about an object's origin inside it, and how deep such a ball overlaps."""
    scene = scene_of(FLOOR + obj("slab", 'shape="box" size="1 1 0.2"', (0, 0, 0.1), fixed=True)
                     + obj("box", 'shape="box" size="0.1 0.2 0.3"', (5, 0, 5))
                     + obj("ball", 'shape="sphere" radius="0.05"', (6, 0, 5))
                     + obj("can", 'shape="cylinder" radius="0.05" height="0.06"', (7, 0, 5))
                     + obj("mug", 'mesh="mug.obj"', (8, 0, 5)))
    c = SceneCollision(scene)
    assert c.inner_radius("box") == pytest.approx(0.05)
    assert c.inner_radius("ball") == pytest.approx(0.05)
    assert c.inner_radius("can") == pytest.approx(0.03)
    assert c.inner_radius("mug") == 0.0  # its origin lies in the cavity
    assert c.inner_radius("floor") == 0.0
    depth, other = c.ball_penetration("box", np.array([[0, 0, 0.23], [0, 0, 0.5], [3, 0, 0.01]]), 0.05)
    assert other == ["slab", None, "floor"]
    np.testing.assert_allclose(depth, [0.02, 0.0, 0.04], atol=1e-6)
    with pytest.raises(GeometryError, match="radius positive"):
        c.ball_penetration("box", np.zeros((1, 3)), 0.0)


def test_a_bead_in_the_handle_hole_is_not_inside_the_mug(mug_body):
    """The convex pieces fill the handle's hole; the exact surfaces decide.

    The mug's body is a cylinder of radius 40 mm about x = -0.014 (outer wall at
    x = 0.026 on the handle side); the handle's hole spans x = 0.026 .. 0.042.
    """
    assert mug_body.bounds[0].tolist() == pytest.approx([-0.054, -0.04, -0.05])
    mug = obj("mug", 'mesh="mug.obj"', (0, 0, 0.05), fixed=True)
    free = SceneCollision(scene_of(mug + obj("bead", 'shape="sphere" radius="0.005"', (0.036, 0, 0.052))))
    assert free.interpenetrations(margin=0.0) == []
    # the pieces alone overlap the bead: the exact surfaces make the difference
    mug_b, bead_b = free._bodies["mug"], free._bodies["bead"]
    assert any(fcl.collide(piece, bead_b.pieces[0], fcl.CollisionRequest(), fcl.CollisionResult())
               for piece in mug_b.pieces)
    # 6 mm to the left it reaches 1 mm into the outer wall
    touching = SceneCollision(scene_of(mug + obj("bead", 'shape="sphere" radius="0.005"', (0.030, 0, 0.052))))
    [(a, b, depth)] = touching.interpenetrations(margin=0.0)
    assert (a, b) == ("mug", "bead") and depth == pytest.approx(0.001, abs=1e-5)


def test_a_ball_in_the_mugs_cavity_touching_its_wall():
    """A ball in the cavity (a 96-gon of radius 28 mm, flat sides 27.985 mm from the axis)."""
    mug = obj("mug", 'mesh="mug.obj"', (0, 0, 0.05), fixed=True)
    inner = 0.028 * math.cos(math.pi / 96)
    free = SceneCollision(scene_of(FLOOR + mug + obj("ball", 'shape="sphere" radius="0.02"', (-0.014, 0, 0.07))))
    assert free.interpenetrations(margin=0.0) == []
    touching = SceneCollision(scene_of(mug + obj("ball", 'shape="sphere" radius="0.03"', (-0.014, 0, 0.07))))
    [(a, b, depth)] = touching.interpenetrations(margin=0.0)
    assert (a, b) == ("mug", "ball")
    assert depth == pytest.approx(0.03 - inner, abs=2e-5)


def test_a_bead_inside_the_mugs_wall_is_found():
    """A bead wholly inside the wall's solid: no surfaces cross, the inside test finds it."""
    mug = obj("mug", 'mesh="mug.obj"', (0, 0, 0.05), fixed=True)
    # the wall runs from 28 mm to 40 mm from the axis (x = -0.014); on -x, away from the handle
    bead = obj("bead", 'shape="sphere" radius="0.004"', (-0.014 - 0.034, 0, 0.06))
    pairs = SceneCollision(scene_of(mug + bead)).interpenetrations(margin=0.0)
    assert [(a, b) for a, b, _ in pairs] == [("mug", "bead")]
    assert pairs[0][2] > 0.004


def test_two_mugs_overlapping_and_apart():
    """Non-convex against non-convex (two BVH surfaces)."""
    a = obj("a", 'mesh="mug.obj"', (0, 0, 0.05))
    near = obj("b", 'mesh="mug.obj"', (0.075, 0, 0.05))  # walls overlap by 5 mm
    far = obj("b", 'mesh="mug.obj"', (0.2, 0, 0.05))
    pairs = SceneCollision(scene_of(FLOOR + a + near)).interpenetrations(margin=0.0)
    assert [(x, y) for x, y, _ in pairs] == [("a", "b")]
    assert 0.001 < pairs[0][2] < 0.03
    assert SceneCollision(scene_of(FLOOR + a + far)).interpenetrations(margin=0.0) == []


def test_batch_of_random_poses_agrees_one_by_one(mug_counter):
    """The batch answer is the candidates' answers one at a time; orientations are normalised."""
    rng = np.random.default_rng(3)
    pos = rng.uniform([-0.6, -0.4, 0.8], [0.6, 0.4, 1.0], (20, 3))
    quat = rng.normal(size=(20, 4)) * 3.0
    hit, depth, other = mug_counter.penetration("mug", pos, quat)
    assert hit.any() and not hit.all()
    for i in range(20):
        h, d, o = mug_counter.penetration("mug", pos[i], quat[i] / 3.0)
        assert h[0] == hit[i] and d[0] == pytest.approx(depth[i], abs=1e-9) and o[0] == other[i]


def test_torch_in_torch_out(mug_counter):
    pos = torch.tensor([[0.0, 0.0, 0.95], [0.0, 0.0, 0.9]], dtype=torch.float32)
    quat = torch.tensor([UP, UP])
    hit, depth, other = mug_counter.penetration("mug", pos, quat)
    assert isinstance(hit, torch.Tensor) and hit.dtype == torch.bool and hit.tolist() == [False, True]
    assert isinstance(depth, torch.Tensor) and depth.shape == (2,)
    assert other == [None, "counter"]


def test_bad_queries_raise_one_line_errors(mug_counter):
    with pytest.raises(GeometryError, match="no object 'cup'"):
        mug_counter.penetration("cup", np.zeros(3), np.array(UP))
    with pytest.raises(GeometryError, match=r"\(B, 3\)"):
        mug_counter.penetration("mug", np.zeros((2, 2)), np.array(UP))
    with pytest.raises(GeometryError, match="non-zero"):
        mug_counter.penetration("mug", np.zeros(3), np.zeros(4))
    with pytest.raises(GeometryError, match="finite"):
        mug_counter.penetration("mug", np.array([np.nan, 0, 0]), np.array(UP))


def test_default_margin_is_a_few_millimetres():
    """What validate accepts as resting contact: more than numerical noise, less than a mistake."""
    assert TOUCHING < DEFAULT_MARGIN <= 0.005


def test_quaternions_are_wxyz():
    """90 degrees about z, written w x y z, turns x into y."""
    r = quat_to_matrix([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(r @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


def test_pieces_cover_a_nonconvex_mesh_and_are_cached(tmp_path):
    """An L-shaped solid: convex pieces that cover it, barely reach outside, and come back from the cache."""
    from dejaview.geometry.distance import depth

    ell = trimesh.boolean.union([trimesh.creation.box(extents=(0.3, 0.1, 0.1)),
                                 trimesh.creation.box(extents=(0.1, 0.3, 0.1),
                                                      transform=trimesh.transformations.translation_matrix(
                                                          (-0.1, 0.1, 0.0)))], engine="manifold")
    path = tmp_path / "ell.obj"
    ell.export(path)
    assert not ell.is_convex
    pieces = load_or_build_pieces(path, cache_dir=tmp_path / "cache")
    assert len(pieces) >= 2 and all(p.is_convex for p in pieces)
    assert sum(p.volume for p in pieces) == pytest.approx(ell.volume, rel=0.05)
    assert -depth(ell, np.vstack([p.vertices for p in pieces])).min() < 1e-4
    assert len(list((tmp_path / "cache").glob("ell-pieces-*.npz"))) == 1
    again = load_or_build_pieces(path, cache_dir=tmp_path / "cache")
    assert [len(p.vertices) for p in again] == [len(p.vertices) for p in pieces]
    # a convex mesh is its own piece
    assert convex_pieces(trimesh.creation.box(extents=(1, 1, 1)))[0].volume == pytest.approx(1.0)


@pytest.mark.parametrize("scene, centre", [("mug_off_counter", (0.0, 0.0, 0.95)),
                                           ("box_among_boxes", (0.85, 0.1, 0.1))])
def test_decide_only_gives_the_same_hits_and_a_lower_bound_of_the_depth(scene, centre):
    """The feasibility check's shortcut (``decide_only``) stops at the first overlap that decides;
    on 400 random poses about the objects it decides as the full search does, and where
    it hits its depth is over the margin and not over the full depth (to the pieces' tolerance)."""
    sc = Scene.from_xml(ROOT / "examples" / "scenes" / f"{scene}.xml")
    c = SceneCollision(sc)
    source = sc.inference.source
    rng = np.random.default_rng(7)
    pos = np.asarray(centre) + rng.uniform(-0.25, 0.25, (400, 3))
    quat = rng.normal(size=(400, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    hit, depth, _ = c.penetration(source, pos, quat, margin=0.003)
    fast_hit, fast_depth, _ = c.penetration(source, pos, quat, margin=0.003, decide_only=True)
    assert 40 < hit.sum() < 360  # both kinds of pose are tried
    np.testing.assert_array_equal(fast_hit, hit)
    # a lower bound of the true depth; the full search's depth of a concave pair comes from fcl's
    # contacts on the true surfaces, which the mug's deepest vertex exceeds by up to 7 um here
    # (within the 0.1 mm the pieces are held to above)
    assert np.all(fast_depth[hit] <= depth[hit] + 1e-4) and np.all(fast_depth[hit] > 0.003)
