"""recon's service logic without a network: frame sets from per-camera images, the learned
detector's path (decoding, a corrupt JPEG, a late camera, a missing detector), and the simulated
path's fitted scene (services/recon/service.py, frameset.py)."""

from __future__ import annotations

import asyncio
import logging
import sys
import types
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from services.recon.frameset import FrameSetBuffer
from services.recon.objects import task_keypoint_names
from services.recon.service import WAITING_SETS, ReconService, decode_window
from services.recon.triangulation import project
from services.world.model import camera_specs
from shared import msgs
from shared.geometry import projection
from shared.runtime.node import Stats


class FakeNode:
    """What ReconService uses of a Node: declared ports as handlers and the messages published per
    output (``published``: the scenes)."""

    def __init__(self) -> None:
        self.handlers: dict[str, object] = {}
        self.outputs: dict[str, list] = {}
        self.published = self.outputs.setdefault("scene", [])
        self.stats = Stats()
        self.log = logging.getLogger("test-recon")
        self.status, self.message = "starting", ""
        self.health_extra = None
        self.publishers: dict[str, set[str]] = {}  # live publishers the info subscription knows of
        self.loop = SimpleNamespace(call_soon=lambda fn: fn())  # deferred work runs at once, unless a test runs a loop

    def input(self, port: str, handler) -> list:
        self.handlers[port] = handler
        return [SimpleNamespace(publishers=self.publishers, key_expr=f"xm/camhub/*/{port}")]

    def output(self, port: str):
        return SimpleNamespace(put=self.outputs.setdefault(port, []).append)

    def set_status(self, status: str, message: str = "") -> None:
        self.status, self.message = status, message

    def handler_failed(self, key: str, exc: Exception) -> None:
        raise exc


def _info(spec, stamp: float, roi: tuple[int, int, int, int] = (0, 0, 0, 0)):
    return msgs.make(
        "sensor_msgs/msg/CameraInfo", header=msgs.header(stamp, spec.name), height=spec.height, width=spec.width,
        distortion_model="plumb_bob", d=np.zeros(5), k=spec.K.ravel(), r=np.eye(3).ravel(),
        p=projection(spec.K, spec.world_T_cam).ravel(), binning_x=0, binning_y=0,
        roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=roi[0], y_offset=roi[1], width=roi[2],
                      height=roi[3], do_rectify=False))


def _jpeg(spec, stamp: float, data: bytes | None = None, size: tuple[int, int] | None = None):
    if data is None:
        w, h = size or (spec.width, spec.height)
        ok, buf = cv2.imencode(".jpg", np.full((h, w, 3), 90, np.uint8))
        data = buf.tobytes()
    return msgs.make("sensor_msgs/msg/CompressedImage", header=msgs.header(stamp, spec.name), format="jpeg",
                     data=np.frombuffer(data, np.uint8))


def test_frame_sets_complete_partial_and_late():
    buf = FrameSetBuffer(late_after=1)
    cams = {"cam0", "cam1", "cam2"}
    assert buf.add(1.0, "cam0", "a", cams) == []
    assert buf.add(1.0, "cam1", "b", cams) == []
    (stamp, images), = buf.add(1.0, "cam2", "c", cams)
    assert stamp == 1.0 and set(images) == cams
    buf.add(2.0, "cam0", "a", cams)
    buf.add(2.0, "cam1", "b", cams)  # cam2 is late for 2.0
    (stamp, images), = buf.add(3.0, "cam0", "a", cams)
    assert stamp == 2.0 and set(images) == {"cam0", "cam1"} and buf.released_partial == 1
    assert buf.add(2.0, "cam2", "c", cams) == [] and buf.dropped_stale == 1


def test_frame_sets_wait_for_camera_infos_running_behind_their_images():
    """Images and CameraInfos come through separate subscriptions: images of newer sets arriving
    before the infos of an older one do not make it late."""
    buf = FrameSetBuffer(late_after=2)
    expected = {"cam0", "cam1", "cam0/info", "cam1/info"}
    for stamp in (1.0, 2.0, 3.0, 4.0):  # four sets of images first
        assert buf.add(stamp, "cam0", "a", expected) == [] and buf.add(stamp, "cam1", "b", expected) == []
    assert buf.add(1.0, "cam0/info", "i", expected) == []
    (stamp, items), = buf.add(1.0, "cam1/info", "j", expected)
    assert stamp == 1.0 and set(items) == expected and buf.released_partial == 0
    # set 2.0's infos are lost: it goes with what it has once two newer sets have both kinds
    assert buf.add(3.0, "cam0/info", "i", expected) == []
    (stamp, items), = buf.add(4.0, "cam0/info", "i", expected)
    assert stamp == 2.0 and set(items) == {"cam0", "cam1"} and buf.released_partial == 1


def test_frame_sets_start_over_when_the_clock_restarts():
    """The world's reset restarts the simulated clock: the new timeline's sets are not late."""
    buf = FrameSetBuffer(late_after=1)
    cams = {"cam0", "cam1"}
    for stamp in (10.0, 10.2, 10.4):
        buf.add(stamp, "cam0", "a", cams)
        buf.add(stamp, "cam1", "b", cams)
    assert buf.add(0.2, "cam0", "a", cams) == [] and buf.dropped_stale == 0
    (stamp, images), = buf.add(0.2, "cam1", "b", cams)
    assert stamp == 0.2 and set(images) == cams and buf.restarts == 1


def test_decode_window_refuses_corrupt_and_wrong_size():
    spec = camera_specs(64, 48)[0]
    model = SimpleNamespace(roi=(8, 4, 32, 24), width=64, height=48)
    ok, buf = cv2.imencode(".jpg", np.zeros((24, 32, 3), np.uint8))
    assert decode_window(buf.tobytes(), model).shape == (24, 32, 3)
    assert decode_window(b"\xff\xd8garbage", model) is None
    ok, buf = cv2.imencode(".jpg", np.zeros((spec.height, spec.width, 3), np.uint8))
    assert decode_window(buf.tobytes(), model) is None  # a full frame where a window was announced


def test_learned_detector_missing_says_how_to_train_and_publishes_nothing(monkeypatch):
    monkeypatch.setitem(sys.modules, "services.recon.learned_detector", None)  # import fails
    node = FakeNode()
    ReconService(node, ReconService.Params(detector="learned"))
    assert node.status == "error" and "xm detector train" in node.message
    assert "image" not in node.handlers and "truth" not in node.handlers, "no truth, and nothing to publish"
    assert node.stats.errors["detector_unavailable"] == 1


@pytest.fixture
def learned(monkeypatch):
    """A stand-in learned detector: projects fixed 3-D points, so the service path can be checked."""
    rng = np.random.default_rng(3)
    names_ = task_keypoint_names("assembly")
    hands = rng.uniform(-0.04, 0.04, (2, 21, 3)) + [[[-0.1, 0.0, 0.06]], [[0.1, 0.0, 0.06]]]  # hand-sized, apart
    points = np.concatenate([hands.reshape(-1, 3), rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.1], (len(names_), 3))])
    seen_views: list[list[str]] = []

    class LearnedDetector:
        names = [f"{h}/{k}" for h in ("left", "right") for k in range(21)] + names_
        object_crops, object_crops_missed, object_crops_unsteady = 4, 1, 2

        def __init__(self, precision: str = "auto") -> None:
            self.requested_precision = precision

        def detect(self, views):
            seen_views.append([v.camera for v in views])
            assert all(v.image.shape == (v.model.roi[3], v.model.roi[2], 3) for v in views)
            uv, _ = project(np.stack([v.model.P for v in views]), points)
            return uv, np.ones(uv.shape[:2])

    module = types.ModuleType("services.recon.learned_detector")
    module.LearnedDetector = LearnedDetector
    monkeypatch.setitem(sys.modules, "services.recon.learned_detector", module)
    return points, seen_views


def test_learned_path_reconstructs_from_images_skipping_corrupt_and_late_cameras(learned):
    points, seen_views = learned
    node = FakeNode()
    ReconService(node, ReconService.Params(detector="learned", fit_hands=False))
    assert node.status == "ok" and "truth" not in node.handlers
    specs = camera_specs(64, 48)
    for spec in specs:  # the rig's cameras are known from their first CameraInfo
        node.handlers["info"](_info(spec, 1.0), f"xm/camhub/{spec.name}/info")
    for spec in specs:  # frame set 1.0: cam3's JPEG is corrupt
        node.handlers["image"](_jpeg(spec, 1.0, b"\xff\xd8bad" if spec.name == "cam3" else None),
                               f"xm/camhub/{spec.name}/image")
    assert len(node.published) == 1
    assert len(node.outputs["tactile_mesh"]) == 1, "a mesh message per frame set, with no hands here"
    assert node.stats.errors["corrupt_jpeg:cam3"] == 1
    assert "cam3" not in seen_views[0] and len(seen_views[0]) == 6
    for spec in specs[:5]:  # frame set 2.0: cam5 and cam6 late; 3.0 and 4.0 begin
        node.handlers["image"](_jpeg(spec, 2.0), f"xm/camhub/{spec.name}/image")
        node.handlers["info"](_info(spec, 2.0), f"xm/camhub/{spec.name}/info")
    for stamp in (3.0, 4.0):
        node.handlers["image"](_jpeg(specs[0], stamp), f"xm/camhub/{specs[0].name}/image")
        assert len(node.published) == 1, "2.0's cameras may still come"
        node.handlers["info"](_info(specs[0], stamp), f"xm/camhub/{specs[0].name}/info")
    assert len(node.published) == 2 and len(seen_views[1]) == 5
    scene = node.published[-1]
    assert list(scene.object_names) == task_keypoint_names("assembly"), "names from the task, not from truth"
    hands = np.asarray(scene.hand_keypoints).reshape(-1, 3)
    np.testing.assert_allclose(hands, points[:42], atol=1e-3)
    assert np.isfinite(np.asarray(scene.object_keypoints)).all()
    assert node.health_extra()["partial_frame_sets"] == 1
    health = node.health_extra()
    assert (health["object_crops"], health["object_crops_missed"], health["object_crops_unsteady"]) == (4, 1, 2)


def test_learned_weights_of_other_keypoints_are_refused(learned):
    sys.modules["services.recon.learned_detector"].LearnedDetector.names = ["left/0", "right/0"]
    node = FakeNode()
    ReconService(node, ReconService.Params(detector="learned"))
    assert node.status == "error" and "make detector" in node.message and "image" not in node.handlers


def test_each_image_is_read_with_the_window_of_its_own_frame_set(learned):
    """camhub moves the windows every frame set: an image must not be read with a newer set's
    CameraInfo that has already arrived (another size, or worse, the same size elsewhere)."""
    _, seen_views = learned
    node = FakeNode()
    windows: list[list[tuple]] = []
    detector = sys.modules["services.recon.learned_detector"].LearnedDetector
    detect = detector.detect
    detector.detect = lambda self, views: (windows.append([v.model.roi for v in views]), detect(self, views))[1]
    ReconService(node, ReconService.Params(detector="learned", fit_hands=False))
    specs = camera_specs(64, 48)
    for stamp, roi in ((1.0, (8, 4, 32, 24)), (2.0, (20, 10, 32, 24)), (3.0, (8, 4, 32, 24))):
        for spec in specs:  # camhub's order: a camera's image, then its CameraInfo
            node.handlers["image"](_jpeg(spec, stamp, size=(32, 24)), f"xm/camhub/{spec.name}/image")
            node.handlers["info"](_info(spec, stamp, roi), f"xm/camhub/{spec.name}/info")
    # set 1.0 came before recon knew the rig; 2.0 is read with its own windows, cam6's included
    # (its image is in before its CameraInfo, while it still holds 1.0's)
    assert windows[-2:] == [[(20, 10, 32, 24)] * 7, [(8, 4, 32, 24)] * 7]
    assert not [k for k in node.stats.errors if k.startswith("corrupt_jpeg")]


def test_a_restarted_recon_waits_for_every_announced_camera_in_its_first_frame_set(learned):
    """A recon started while camhub runs knows the cameras from their publishers' tokens: its first
    frame set is not released with the one camera whose CameraInfo came first."""
    _, seen_views = learned
    node = FakeNode()
    ReconService(node, ReconService.Params(detector="learned", fit_hands=False))
    specs = camera_specs(64, 48)
    node.publishers.update({f"xm/camhub/{s.name}/info": {"token"} for s in specs})
    for spec in specs:
        node.handlers["image"](_jpeg(spec, 1.0), f"xm/camhub/{spec.name}/image")
        node.handlers["info"](_info(spec, 1.0), f"xm/camhub/{spec.name}/info")
    assert len(node.published) == 1 and seen_views == [[s.name for s in specs]]
    assert node.stats.errors["too_few_cameras"] == 0


def test_a_spare_loads_the_network_before_it_takes_over(learned):
    """prepare() (a standby spare) builds the detector; the service started later uses that one."""
    cls = sys.modules["services.recon.learned_detector"].LearnedDetector
    built: list[object] = []
    cls.__init__ = lambda self, *a, **kw: built.append(self)
    params = ReconService.Params(detector="learned", fit_hands=False)
    ReconService.prepare(params)
    assert len(built) == 1
    service = ReconService(FakeNode(), params)
    assert len(built) == 1 and service.learned is built[0], "the prepared network, not a second load"
    ReconService(FakeNode(), params)
    assert len(built) == 2, "a prepared network serves one start only"


def test_a_recon_behind_the_cameras_detects_the_newest_waiting_sets_in_order_and_counts_the_ones_it_skipped(learned):
    """On the loop, detection waits for the samples already queued: of three complete sets handed
    in one batch (recon was busy while they came) the two newest are detected, oldest first, and
    the first is counted as skipped."""
    _, seen_views = learned
    node = FakeNode()
    service = ReconService(node, ReconService.Params(detector="learned", fit_hands=False))
    specs = camera_specs(64, 48)

    async def batch() -> None:
        node.loop = asyncio.get_running_loop()
        for stamp in (1.0, 2.0, 3.0):
            for spec in specs:
                node.handlers["image"](_jpeg(spec, stamp), f"xm/camhub/{spec.name}/image")
                node.handlers["info"](_info(spec, stamp), f"xm/camhub/{spec.name}/info")
        assert node.published == [], "detection waits until the queued samples are in"
        for _ in range(4):
            await asyncio.sleep(0)

    asyncio.run(batch())
    assert len(seen_views) == WAITING_SETS
    assert [msgs.stamp_seconds(m.header.stamp) for m in node.published] == [2.0, 3.0]
    assert service._health()["frame_sets_behind"] == 1


def test_a_detector_graph_running_without_its_int8_copy_is_reported(learned, caplog):
    """A stale or missing int8 graph leaves recon running on the float one: @health and the log say which and why."""
    cls = sys.modules["services.recon.learned_detector"].LearnedDetector
    why = "float32 (model.int8.onnx was made from other weights; run `xm detector quantize` again)"
    cls.__init__ = lambda self, *a, **kw: setattr(self, "precision", {"model": why, "hands": "int8"})
    node = FakeNode()
    with caplog.at_level(logging.WARNING, logger="test-recon"):
        service = ReconService(node, ReconService.Params(detector="learned", fit_hands=False))
    assert service._health()["detector_precision"] == {"model": why, "hands": "int8"}
    warned = [r.getMessage() for r in caplog.records if "detector graph" in r.getMessage()]
    assert warned == [f"detector graph model runs as {why}"]
