"""Tactile projection (thesis 5.7): the hand mesh posed from keypoints, the glove's cells mapped onto
it, padding and bicubic sampling, the TactileMesh message, and recon publishing it
(services/recon/hand_mesh.py, tactile_projection.py, service.py)."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from services.glove.layout import CELL_MASK, CELL_REGION, FINGER_ROWS, pressure_from_forces, region_pressure_kpa
from services.panel import view
from services.recon.hand_mesh import CHAINS, PALM, RADIUS, bone_frames, pose, template
from services.recon.hand_model import local_points, mirror, rodrigues
from services.recon.objects import task_keypoint_names
from services.recon.service import ReconService
from services.recon.tactile_projection import FINGERS, TactileProjector
from services.recon.triangulation import project
from services.world.model import camera_specs
from shared import msgs
from shared.demo import TACTILE_REGIONS
from shared.runtime.validate import check
from tests.unit.test_recon_service_paths import FakeNode, _info, _jpeg
from tests.unit.test_recon_stages import _shape

PALM_REGION = TACTILE_REGIONS.index("palm")


def hand(side: str = "right", curl: float = 0.3, rot=(0.3, -0.2, 1.0), at=(0.1, 0.2, 0.3)) -> np.ndarray:
    """World keypoints (21,3) of a posed hand."""
    joints = np.tile([0.05, curl, curl, 0.7 * curl], 5).reshape(5, 4)
    return (local_points(_shape(), joints) @ mirror(side)) @ rodrigues(np.array(rot)).T + np.array(at)


@pytest.fixture(scope="module")
def projector() -> TactileProjector:
    return TactileProjector()


def _signed_volumes(verts: np.ndarray, faces: np.ndarray, part: np.ndarray) -> np.ndarray:
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6
    return np.array([vol[part == k].sum() for k in np.unique(part)])


@pytest.mark.parametrize("side", ["right", "left"])
def test_mesh_is_closed_and_faces_outward_on_either_hand(side):
    t = template()
    faces = t.faces(side)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert (count == 2).all(), "every edge joins exactly two triangles (closed surfaces)"
    verts = pose(hand(side), side)
    vols = _signed_volumes(verts, faces, t.chain[faces[:, 0]])
    assert len(vols) == 6 and (vols > 2e-6).all(), f"palm and five fingers enclose positive volumes: {vols}"


def test_mesh_poses_with_the_hand():
    t = template()
    kp = hand(curl=0.9)
    verts = pose(kp, "right")
    tube = (t.chain >= 0) & (t.u < 1)
    c, j = t.chain[tube], t.bone[tube]
    a, b = kp[CHAINS[c, j]], kp[CHAINS[c, j + 1]]
    s = np.clip(np.einsum("ij,ij->i", verts[tube] - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
    dist = np.linalg.norm(verts[tube] - (a + s[:, None] * (b - a)), axis=1)
    assert dist.max() < RADIUS.max() + 1e-4, "finger vertices hug their bones"
    tips = (t.chain >= 0) & (t.u == 1)
    tip_dist = np.linalg.norm(verts[tips] - kp[CHAINS[t.chain[tips], 3]], axis=1)
    assert tip_dist.max() < 1.01 * RADIUS.max(), "the dome sits on the tip keypoint"
    R, shift = rodrigues(np.array([0.4, 1.1, -0.7])), np.array([0.3, -0.1, 0.2])
    np.testing.assert_allclose(pose(kp @ R.T + shift, "right"), verts @ R.T + shift, atol=1e-9)
    moved = pose(hand(curl=0.1), "right")
    assert np.linalg.norm(moved - verts, axis=1)[t.chain >= 1].max() > 0.02, "curling moves the fingers"


def test_bone_frames_follow_the_bones_and_point_to_the_thumb_on_either_hand():
    for side in ("right", "left"):
        kp = hand(side)
        R, frames = bone_frames(kp, side)
        d = kp[CHAINS[:, 1:]] - kp[CHAINS[:, :-1]]
        np.testing.assert_allclose(frames[..., :, 0], d / np.linalg.norm(d, axis=-1, keepdims=True), atol=1e-9)
        toward_thumb = kp[1] - kp[17]
        assert R[:, 1] @ toward_thumb > 0, f"{side}: y points toward the thumb"


def _lit(projector: TactileProjector, cells: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Vertices above half the pressure of the pressed cells, and every vertex's pressure."""
    p = np.zeros((16, 16))
    p[cells] = 20.0
    values = projector.sample(p)
    return values > 10.0, values


@pytest.mark.parametrize("finger", FINGERS)
def test_a_pressed_cell_lights_its_finger_segment(projector, finger):
    t, chain, r0 = projector.template, FINGERS.index(finger), FINGER_ROWS[finger]
    along = t.along()
    first, last = (1.0, 3.0) if finger == "thumb" else (0.0, 3.0)
    for col, (lo, hi) in ((0, (first, first + (last - first) / 6)), (5, (last - (last - first) / 6, last))):
        lit, values = _lit(projector, (slice(r0, r0 + 2), col))
        assert lit.sum() >= 6, f"{finger} col {col}: too few vertices lit"
        assert (t.chain[lit] == chain).all(), f"{finger} col {col} lit another part"
        assert (along[lit] >= lo - 0.1).all() and (along[lit] <= hi + 0.1).all(), \
            f"{finger} col {col}: lit along {along[lit].min():.2f}..{along[lit].max():.2f}, expected {lo}..{hi}"
        assert (np.abs(t.angle[lit]) <= np.pi / 2).all(), "sensors sit on the palmar side"
    lit, _ = _lit(projector, (r0, slice(0, 6)))  # the first row: the thumb's side of the finger
    assert (t.angle[lit] > 0).all()


@pytest.mark.parametrize("side", ["right", "left"])
def test_the_pressed_finger_lights_where_it_is_on_the_posed_hand(projector, side):
    kp = hand(side)
    verts, _, values = projector.hand(kp, side, pressure_from_forces(np.array([0, 0, 0, 0, 1.0, 0])))  # little
    lit = verts[values > 1.0]
    little = np.linalg.norm(lit - kp[17:21].mean(axis=0), axis=1).mean()
    index = np.linalg.norm(lit - kp[5:9].mean(axis=0), axis=1).mean()
    assert little < 0.5 * index
    axis = kp[17] - kp[0]
    curl = kp[20] - kp[17] - (kp[20] - kp[17]) @ axis / (axis @ axis) * axis  # fingers curl toward the palm
    assert ((lit - kp[17:21].mean(axis=0)) @ curl).mean() > 0, "the sensor sits on the side the finger curls to"
    t = projector.template
    palm, back = projector.region == PALM_REGION, (t.chain == PALM) & (t.offset[:, 2] > 0)
    axis = kp[9] - kp[0]
    curl = kp[12] - kp[9] - (kp[12] - kp[9]) @ axis / (axis @ axis) * axis  # the middle finger's
    assert (verts[palm].mean(axis=0) - verts[back].mean(axis=0)) @ curl / np.linalg.norm(curl) > 0.01, \
        "the palm sensor faces the way the fingers curl, the back of the hand the other way"


def test_palm_rows_run_from_the_wrist_and_columns_from_the_little_finger(projector):
    kp = hand()
    verts = pose(kp, "right")
    for cells, near, far in (((0, slice(0, 3)), kp[0], kp[[5, 9, 13, 17]].mean(axis=0)),
                             ((slice(0, 4), 0), kp[17], kp[5])):
        lit, _ = _lit(projector, cells)
        assert (projector.template.chain[lit] == PALM).all() and lit.sum() >= 4
        assert np.linalg.norm(verts[lit] - near, axis=1).mean() < np.linalg.norm(verts[lit] - far, axis=1).mean()


def test_the_palm_cutout_senses_nothing(projector):
    t, rc = projector.template, projector.rc
    palmar = (t.chain == PALM) & (t.offset[:, 2] < 0)
    over_cutout = palmar & (np.rint(rc[:, 0]) >= 4) & (np.rint(rc[:, 1]) >= 3)
    assert over_cutout.sum() >= 4 and not projector.sensed[over_cutout].any()
    assert projector.sensed[palmar & ~over_cutout].all()
    assert set(np.unique(CELL_MASK[4:6, 3:6])) == {0}, "the glove's layout has the cutout there"
    values = projector.sample(np.full((16, 16), 7.0))
    assert (values[over_cutout] == 0).all()


def test_padding_keeps_each_sensor_to_its_own_cells(projector):
    p = np.zeros((16, 16))
    p[CELL_REGION == TACTILE_REGIONS.index("thumb")] = 30.0  # rows 6-7, next to the palm and the index
    values = projector.sample(p)
    thumb = projector.region == TACTILE_REGIONS.index("thumb")
    np.testing.assert_allclose(values[thumb], 30.0, atol=1e-4)
    assert (values[~thumb] == 0).all(), "the index (rows 8-9) and the palm (rows 0-5) read none of it"
    garbage = np.where(CELL_MASK == 1, 0.0, 1e4)  # unpopulated crossings, the cutout, unused lines
    assert (projector.sample(garbage) == 0).all()


def test_bicubic_reproduces_a_constant_and_is_smooth(projector):
    values = projector.sample(np.where(CELL_MASK == 1, 12.5, -50.0))
    np.testing.assert_allclose(values[projector.sensed], 12.5, atol=1e-4)
    assert (values[~projector.sensed] == 0).all()
    r0 = FINGER_ROWS["middle"]
    ramp = np.zeros((16, 16))
    ramp[r0:r0 + 2, 0:6] = 2.0 * np.arange(6)  # 0, 2, ... 10 kPa from the base to the tip
    values = projector.sample(ramp)
    mid = projector.region == TACTILE_REGIONS.index("middle")
    col = projector.rc[mid, 1]
    order = np.argsort(col)
    assert (np.diff(values[mid][order]) >= -1e-4).all(), "monotone along the finger"
    inner = (col >= 0) & (col <= 5)
    np.testing.assert_allclose(values[mid][inner], 2.0 * col[inner], atol=0.25)  # close to the linear ramp


def test_the_worlds_pressed_regions_light_their_parts(projector):
    forces = np.array([1.5, 1.5, 0, 0, 0, 0])  # the teacher's grasp: thumb and index
    values = projector.sample(pressure_from_forces(forces))
    per_cell = region_pressure_kpa(forces)
    for k, name in enumerate(TACTILE_REGIONS):
        part = projector.region == k
        assert part.any()
        np.testing.assert_allclose(values[part], per_cell[k], atol=1e-3, err_msg=name)


def test_tactile_mesh_message_round_trip(projector):
    hands = np.stack([hand("left"), hand("right", at=(0.3, 0.2, 0.3))])
    mask = np.ones((2, 21), np.uint8)
    p = pressure_from_forces(np.array([0, 2.0, 0, 0, 0, 0]))
    msg, skipped = projector.message(4.5, ["left", "right"], hands, mask, {"right": p})
    assert skipped == {}
    back = msgs.deserialize(msgs.serialize(msg), "xm_msgs/msg/TactileMesh")
    assert msgs.stamp_seconds(back.header.stamp) == 4.5 and list(back.hand_names) == ["right"]
    (name, verts, faces, pressure), = view.tactile_mesh_arrays(back.hand_names, back.vertex_count, back.vertices,
                                                              back.faces, back.pressure)
    v, f, s = projector.hand(hands[1], "right", p)
    assert name == "right"
    np.testing.assert_allclose(verts, v, atol=1e-6)
    np.testing.assert_array_equal(faces, f)
    np.testing.assert_allclose(pressure, s, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(back.sensed, bool), projector.sensed)

    mask[1, 7] = 0  # a hand with a keypoint missing is left out, and said so
    msg, skipped = projector.message(4.6, ["left", "right"], hands, mask, {"right": p, "left": p})
    assert list(msg.hand_names) == ["left"] and skipped == {"right": "incomplete_hand"}
    msg, skipped = projector.message(4.7, ["left", "right"], hands, np.ones((2, 21)), {"left": np.zeros(12)})
    assert list(msg.hand_names) == [] and skipped == {"left": "bad_input"}
    # No hand to mesh is still a message, one per frame set: valid, and nothing for the panel to draw.
    back = msgs.deserialize(msgs.serialize(msg), "xm_msgs/msg/TactileMesh")
    check(back, "xm_msgs/msg/TactileMesh", None)  # the receivers' validation accepts it
    assert back.vertex_count == len(projector.sensed) and len(back.vertices) == len(back.faces) == 0
    assert view.tactile_mesh_arrays(back.hand_names, back.vertex_count, back.vertices, back.faces,
                                    back.pressure) == []
    msg, skipped = projector.message(4.8, ["left", "right"], hands, mask, {})
    assert list(msg.hand_names) == [] and skipped == {}, "no glove frame: no hand, nothing skipped"


def test_recon_publishes_the_gloved_hands_mesh(monkeypatch):
    """The service path: a glove frame for the right hand, a frame set -> a TactileMesh of that hand."""
    kp = np.concatenate([hand("left", at=(-0.1, 0.0, 0.1)), hand("right", at=(0.1, 0.0, 0.1))])
    objects = np.zeros((len(task_keypoint_names(ReconService.Params().task)), 3))

    class LearnedDetector:  # a stand-in: projects the two hands (and objects at the origin)
        names = [f"{h}/{k}" for h in ("left", "right") for k in range(21)] + task_keypoint_names("assembly")

        def __init__(self, precision: str = "auto") -> None:
            self.requested_precision = precision

        def detect(self, views):
            pts = np.concatenate([kp, objects])
            uv, _ = project(np.stack([v.model.P for v in views]), pts)
            return uv, np.ones(uv.shape[:2])

    module = types.ModuleType("services.recon.learned_detector")
    module.LearnedDetector = LearnedDetector
    monkeypatch.setitem(sys.modules, "services.recon.learned_detector", module)
    node = FakeNode()
    ReconService(node, ReconService.Params(detector="learned", fit_hands=False))
    specs = camera_specs(64, 48)
    for spec in specs:
        node.handlers["info"](_info(spec, 0.0), f"xm/camhub/{spec.name}/info")
    pressure = pressure_from_forces(np.array([0, 0, 0, 0, 0, 3.0]))  # the palm
    node.handlers["tactile"](msgs.make("xm_msgs/msg/Tactile", header=msgs.header(1.0), hand="right", rows=16, cols=16,
                                       pressure=pressure.astype(np.float32).ravel(), mask=CELL_MASK.ravel(),
                                       sequence=1))
    for t in (1.0, 2.0):  # the glove frame is fresh for the first frame set only
        for spec in specs:  # camhub's order: a camera's image, then its frame set's CameraInfo
            node.handlers["image"](_jpeg(spec, t), f"xm/camhub/{spec.name}/image")
            node.handlers["info"](_info(spec, t), f"xm/camhub/{spec.name}/info")
    meshes = node.outputs["tactile_mesh"]
    assert len(meshes) == 2 and len(node.published) == 2  # one mesh per frame set, beside its scene
    assert list(meshes[1].hand_names) == [], "the glove frame is stale for the second set: no hand"
    (name, verts, _, values), = view.tactile_mesh_arrays(meshes[0].hand_names, meshes[0].vertex_count,
                                                         meshes[0].vertices, meshes[0].faces, meshes[0].pressure)
    assert name == "right"
    palm = TactileProjector().region == PALM_REGION
    assert (values[palm] > 1.0).all() and (values[~palm] == 0).all()
    np.testing.assert_allclose(verts, pose(kp[21:], "right"), atol=2e-3)  # from the triangulated keypoints
    assert "tactile_mesh" in node.health_extra()["stage_ms_median"]
