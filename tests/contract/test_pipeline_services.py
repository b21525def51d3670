"""Contract tests of the pipeline services, each a process seen only through Zenoh."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from learning.ours import train
from learning.presets import preset
from services.world.model import camera_specs
from services.world.teacher import generate_demo
from shared import msgs
from shared.geometry import projection
from shared.kinematics import load_robot
from shared.robots.registry import describe
from tests.conftest import ServiceProcess, query_json, wait_for, wait_until, write_deployment


def collect(session, key: str, msgtype: str) -> tuple[list, object]:
    out: list = []
    sub = session.declare_subscriber(key, lambda s: out.append(msgs.deserialize(s.payload.to_bytes(), msgtype)))
    return out, sub


def world_params(tmp_path: Path) -> dict:
    run = tmp_path / "run"
    return {"glove_ports": [str(run / "glove-left"), str(run / "glove-right")], "robot_port": str(run / "board")}


def test_world_publishes_clock_truth_session_and_hosts_devices(router, tmp_path):
    endpoint, session = router
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"world": {"sim": world_params(tmp_path)}}, clock="sim")
    svc = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    try:
        clocks, _a = collect(session, "xm/clock", "rosgraph_msgs/msg/Clock")
        truths, _b = collect(session, "xm/world/sim/truth", "xm_msgs/msg/GroundTruth")
        assert wait_for(lambda: len(truths) > 20, 30), svc.output()
        times = [msgs.stamp_seconds(c.clock) for c in clocks]
        assert np.all(np.diff(times) > 0)
        t = truths[-1]
        assert len(t.hand_keypoints) == 2 * 21 * 3 and "camera/connector" in t.object_names
        for name in ("glove-left", "glove-right", "board"):
            assert (tmp_path / "run" / name).is_symlink()
        bad = query_json(session, "xm/world/sim/@cmd/mode", {"mode": "dance"})
        assert bad and not bad[0]["ok"] and "teacher" in bad[0]["error"]
        # the dashboard's executions: robot mode (the teacher's hands leave), the task's success test, back
        assert query_json(session, "xm/world/sim/@cmd/mode", {"mode": "robot"})[0]["ok"]
        assert wait_for(lambda: not np.any(truths[-1].hand_keypoints), 10), "the hands left the cell in robot mode"
        [out] = query_json(session, "xm/world/sim/@cmd/outcome", {})
        assert out["ok"] and out["task"] == "assembly" and out["mode"] == "robot" and out["success"] is False
        assert out["seated"] is False and 5.0 < out["connector_gap_mm"] < 1000.0  # nobody assembled anything
        assert query_json(session, "xm/world/sim/@cmd/mode", {"mode": "teacher"})[0]["ok"]
        assert wait_for(lambda: np.any(truths[-1].hand_keypoints), 10), "the teacher's hands back"
    finally:
        assert svc.stop() in (0, -15), svc.output()


def test_camhub_publishes_synchronized_jpeg_and_camera_info(router, tmp_path):
    endpoint, session = router
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"world": {"sim": world_params(tmp_path)},
                                                           "camhub": {"main": {"rate_hz": 5.0}}}, clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    cam = ServiceProcess("camhub", dep, "main", tmp_path / "camhub.log")
    try:
        images, _a = collect(session, "xm/camhub/*/image", "sensor_msgs/msg/CompressedImage")
        infos, _b = collect(session, "xm/camhub/*/info", "sensor_msgs/msg/CameraInfo")
        assert wait_for(lambda: len(images) >= 14, 60), cam.output()
        stamps = {}
        for m in images[:14]:
            stamps.setdefault(msgs.stamp_seconds(m.header.stamp), set()).add(m.header.frame_id)
        assert any(len(v) == 7 for v in stamps.values()), "seven cameras share one trigger stamp"
        rgb = cv2.imdecode(np.frombuffer(bytes(images[0].data), np.uint8), cv2.IMREAD_COLOR)
        assert rgb.shape == (240, 320, 3) and rgb.std() > 5
        info = infos[0]
        P = np.asarray(info.p).reshape(3, 4)
        u, v, w = P @ [0.0, 0.0, 0.0, 1.0]
        assert 0 < u / w < info.width and 0 < v / w < info.height
    finally:
        cam.stop()
        world.stop()


def test_recon_triangulates_the_scene_from_cameras_and_detections(router, tmp_path):
    """The simulated detector's path (projected truth, an experiment option)."""
    endpoint, session = router
    dep = write_deployment(tmp_path / "d.toml", endpoint,
                           {"recon": {"main": {"detector": "simulated", "dropout": 0.0}}})
    svc = ServiceProcess("recon", dep, "main", tmp_path / "recon.log")
    try:
        scenes, _a = collect(session, "xm/recon/main/scene", "xm_msgs/msg/Scene")
        assert wait_for(lambda: query_json(session, "xm/recon/main/@health"), 20), svc.output()
        rng = np.random.default_rng(0)
        hands = rng.uniform([-0.1, -0.1, 0.02], [0.1, 0.1, 0.15], (42, 3)).astype(np.float32)
        objects = rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.01], (3, 3)).astype(np.float32)
        now = time.time()
        header = msgs.header(now)
        infos = [msgs.serialize(msgs.make(
            "sensor_msgs/msg/CameraInfo", header=msgs.header(now, spec.name), height=240, width=320,
            distortion_model="plumb_bob", d=np.zeros(5), k=spec.K.ravel(), r=np.eye(3).ravel(),
            p=projection(spec.K, spec.world_T_cam).ravel(), binning_x=0, binning_y=0,
            roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                          do_rectify=False))) for spec in camera_specs()]
        truth = msgs.serialize(msgs.make(
            "xm_msgs/msg/GroundTruth", header=header, hand_names=["left", "right"],
            hand_keypoints=hands.ravel(), hand_visible=np.ones(42, np.uint8),
            object_names=["a/0", "a/1", "b/0"], object_keypoints=objects.ravel(),
            object_visible=np.array([1, 1, 0], np.uint8), body_names=[], body_poses=np.zeros(0, np.float32),
            contact_forces=np.zeros(12, np.float32)))
        wanted = {f"xm/camhub/{spec.name}/info" for spec in camera_specs()} | {"xm/world/sim/truth"}

        def cameras_and_truth_received() -> bool:
            for spec, info in zip(camera_specs(), infos, strict=True):
                session.put(f"xm/camhub/{spec.name}/info", info)
            session.put("xm/world/sim/truth", truth)
            return wanted <= set(query_json(session, "xm/recon/main/@health")[0]["received_hz"])

        wait_until(cameras_and_truth_received, 20, "recon to receive every camera and the truth", period=0.2)
        # The subscription keeps only the latest image: the malformed one is seen alone, then a good one.
        session.put("xm/camhub/cam0/image", b"\x00\x01garbage")  # malformed: counted, not fatal
        wait_until(lambda: any(k.startswith("malformed") for k in
                               query_json(session, "xm/recon/main/@health")[0]["errors"]), 10, "garbage counted")
        image = msgs.serialize(msgs.make(
            "sensor_msgs/msg/CompressedImage", header=header, format="jpeg", data=np.zeros(4, np.uint8)))
        wait_until(lambda: session.put("xm/camhub/cam0/image", image) or scenes, 10,
                   lambda: f"a scene: {svc.output()}", period=0.2)
        s = scenes[-1]
        est = np.asarray(s.hand_keypoints).reshape(42, 3)
        assert np.median(np.linalg.norm(est - hands, axis=1)) < 0.005
        assert list(s.object_mask) == [1, 1, 0], "truth-occluded point comes back masked"
    finally:
        assert svc.stop() in (0, -15), svc.output()


def test_policy_and_trajopt_turn_a_scene_into_a_plan_and_a_joint_trajectory(router, tmp_path):
    endpoint, session = router
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"policy": {"main": {}}, "trajopt": {"main": {}}})
    policy = ServiceProcess("policy", dep, "main", tmp_path / "policy.log")
    trajopt = ServiceProcess("trajopt", dep, "main", tmp_path / "trajopt.log")
    try:
        plans, _a = collect(session, "xm/policy/main/plan", "xm_msgs/msg/Plan")
        trajs, _b = collect(session, "xm/trajopt/main/trajectory", "trajectory_msgs/msg/JointTrajectory")
        from services.world.teacher import generate_demo

        demo = generate_demo("assembly", 5)
        names = load_robot("workcell").joint_names
        q = np.zeros(len(names))
        q[[2, 8]] = 0.2
        assert wait_for(lambda: query_json(session, "xm/policy/main/@health") and
                        query_json(session, "xm/trajopt/main/@health"), 60), policy.output() + trajopt.output()
        def inputs_published() -> bool:  # trajopt holds before the first plan
            now = time.time()
            session.put("xm/world/sim/session", msgs.serialize(msgs.make(
                "xm_msgs/msg/Session", header=msgs.header(now), task="assembly", demo=0, phase="approach",
                tactile_hand="left", seed_layout="{}")))
            session.put("xm/recon/main/scene", msgs.serialize(msgs.make(
                "xm_msgs/msg/Scene", header=msgs.header(now), hand_names=["left", "right"],
                hand_keypoints=demo.hands[0].ravel(), hand_mask=np.ones(42, np.uint8),
                object_names=demo.object_names, object_keypoints=demo.objects[0].ravel(),
                object_mask=np.ones(len(demo.object_names), np.uint8), tactile_regions=[],
                tactile=np.zeros(0, np.float32), tactile_mask=np.zeros(0, np.uint8))))
            session.put("xm/robot/workcell/state", msgs.serialize(msgs.make(
                "sensor_msgs/msg/JointState", header=msgs.header(now), name=names, position=q,
                velocity=np.zeros(len(q)), effort=np.zeros(len(q)))))
            session.put("xm/policy/main/plan", b"broken plan")  # counted by trajopt
            return bool(plans and trajs)

        wait_until(inputs_published, 30, lambda: f"a plan and a trajectory: {policy.output()}{trajopt.output()}",
                   period=0.2)
        p = plans[-1]
        assert p.steps == 11 and len(p.point_names) == 42 and np.isfinite(p.positions).all()
        t = trajs[-1]
        assert list(t.joint_names) == names and len(t.points) == 20
        model = load_robot("workcell")
        for point in t.points:
            assert np.all(np.asarray(point.positions) >= model.lower - 1e-6)
            assert np.all(np.asarray(point.positions) <= model.upper + 1e-6)

        def broken_plan_counted() -> bool:  # keep-latest: a valid plan may supersede a broken one
            session.put("xm/policy/main/plan", b"broken plan")
            health = query_json(session, "xm/trajopt/main/@health")
            return bool(health) and "solve_time_ms" in health[0] and any(
                k.startswith("malformed") for k in health[0]["errors"])

        assert wait_for(broken_plan_counted, 10), trajopt.output()
    finally:
        policy.stop()
        trajopt.stop()


def test_trajopt_runs_the_hand_arm_from_its_own_state_key_with_the_hand_pose_prior(router, tmp_path):
    """robot = "hand_arm": trajopt reads xm/robot/hand_arm/state (not the gantry's key), tracks the
    right hand's wrist and fingertips of a plan with coupled finger joints, and says that the 7.22
    prior is on."""
    hand_arm = describe("hand_arm")
    HAND_ARM_MAP = hand_arm.point_map

    endpoint, session = router
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"trajopt": {"main": {"robot": "hand_arm"}}})
    trajopt = ServiceProcess("trajopt", dep, "main", tmp_path / "trajopt.log")
    model = load_robot("hand_arm")
    names = model.joint_names
    q0 = model.couple(np.array([hand_arm.home.get(n, 0.0) for n in names]))
    target = q0.copy()
    target[names.index("elbow")] -= 0.15
    for finger in ("index", "middle", "ring"):
        target[names.index(f"{finger}_j2")] = target[names.index(f"{finger}_j3")] = 0.6
    frames = list(HAND_ARM_MAP.values())
    goal = np.array([model.fk(target)[f][:3, 3] for f in frames])
    start_error = np.linalg.norm(np.array([model.fk(q0)[f][:3, 3] for f in frames]) - goal, axis=1).max()
    try:
        trajs, _a = collect(session, "xm/trajopt/main/trajectory", "trajectory_msgs/msg/JointTrajectory")
        assert wait_for(lambda: query_json(session, "xm/trajopt/main/@health"), 60), trajopt.output()
        def tracking_error() -> float:
            now = time.time()
            session.put("xm/robot/hand_arm/state", msgs.serialize(msgs.make(
                "sensor_msgs/msg/JointState", header=msgs.header(now), name=names, position=q0,
                velocity=np.zeros(len(q0)), effort=np.zeros(len(q0)))))
            session.put("xm/robot/workcell/state", msgs.serialize(msgs.make(  # another robot: not ours
                "sensor_msgs/msg/JointState", header=msgs.header(now), name=["left_x"], position=np.zeros(1),
                velocity=np.zeros(1), effort=np.zeros(1))))
            session.put("xm/policy/main/plan", msgs.serialize(msgs.make(
                "xm_msgs/msg/Plan", header=msgs.header(now), policy="test", dt=0.1, steps=21,
                point_names=list(HAND_ARM_MAP), positions=np.tile(goal.ravel(), 21).astype(np.float32),
                mask=np.ones(21 * len(frames), np.uint8), efforts=np.zeros(0, np.float32))))
            if not trajs:
                return np.inf
            q = np.asarray(trajs[-1].points[-1].positions)
            return np.linalg.norm(np.array([model.fk(q)[f][:3, 3] for f in frames]) - goal, axis=1).max()

        wait_until(lambda: tracking_error() < start_error / 3, 30,
                   lambda: f"trajectories a third of the way to the goal: {trajopt.output()}", period=0.2)
        assert list(trajs[-1].joint_names) == names
        q = np.asarray(trajs[-1].points[-1].positions)
        for finger in ("thumb", "index", "middle", "ring"):
            assert q[names.index(f"{finger}_j3")] == pytest.approx(q[names.index(f"{finger}_j2")])
        health = query_json(session, "xm/trajopt/main/@health")[0]
        assert health["robot"] == "hand_arm" and health["pose_prior"] is True
        received = health["received_hz"]
        assert "xm/robot/hand_arm/state" in received and "xm/robot/workcell/state" not in received
        assert "state_missing_joint" not in health["errors"] and health["status"] == "ok"
    finally:
        trajopt.stop()


def _scene_msg(demo, k: int, now: float, hide: int | None = None):
    mask = np.ones(42, np.uint8)
    hands = demo.hands[k].reshape(42, 3).copy()
    if hide is not None:  # an occluded point arrives as zeros with mask 0 (NaN is refused on the wire)
        mask[hide], hands[hide] = 0, 0.0
    return msgs.serialize(msgs.make(
        "xm_msgs/msg/Scene", header=msgs.header(now), hand_names=["left", "right"],
        hand_keypoints=hands.ravel(), hand_mask=mask, object_names=demo.object_names,
        object_keypoints=demo.objects[k].ravel(), object_mask=np.ones(len(demo.object_names), np.uint8),
        tactile_regions=[], tactile=np.zeros(0, np.float32), tactile_mask=np.zeros(0, np.uint8)))


@pytest.mark.slow  # trains a small network first: ~40 s
def test_policy_serves_a_trained_network_and_falls_back_to_naive_without_one(router, tmp_path):
    """method = "learned": horizons of the network (hands and objects) at the plan rate; a missing
    checkpoint degrades to the naive baseline and says so."""
    endpoint, session = router
    demos = [generate_demo("assembly", s, index=i) for i, s in enumerate((11, 12))]
    train(preset("no_tactile", steps=20, hidden=(64, 64), batch=32, eval_every=10_000), demos, None, tmp_path,
          progress=False)
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"policy": {
        "main": {"method": "learned", "checkpoint": str(tmp_path / "policy.pt"), "rate_hz": 5.0},
        "other": {"method": "learned", "checkpoint": str(tmp_path / "missing.pt")}}})
    learned = ServiceProcess("policy", dep, "main", tmp_path / "policy.log")
    fallback = ServiceProcess("policy", dep, "other", tmp_path / "other.log")
    try:
        plans, _a = collect(session, "xm/policy/*/plan", "xm_msgs/msg/Plan")  # both instances' plans
        naive = lambda: [p for p in plans if p.policy == "naive"]  # noqa: E731
        assert wait_for(lambda: query_json(session, "xm/policy/main/@health"), 60), learned.output()
        k = 0

        def scene_sent() -> int:
            nonlocal k
            now = time.time()
            session.put("xm/world/sim/session", msgs.serialize(msgs.make(  # the naive replay starts an episode
                "xm_msgs/msg/Session", header=msgs.header(now), task="assembly", demo=0, phase="approach",
                tactile_hand="left", seed_layout="{}")))
            session.put("xm/recon/main/scene", _scene_msg(demos[0], k, now, hide=8 if k % 2 else None))
            k += 1
            return len([p for p in plans if p.policy.startswith("learned")]) >= 3 and naive()

        wait_until(scene_sent, 20, lambda: f"three plans of the network and one of the fallback: {learned.output()}"
                   f"{fallback.output()}", period=0.1)
        ours = [p for p in plans if p.policy == "learned:no_tactile"]
        assert len(ours) >= 3, [p.policy for p in plans]
        p = ours[-1]
        n_obj = len(demos[0].object_names)
        assert len(p.point_names) == 42 + n_obj and p.point_names[42].startswith("object/")
        assert p.steps == 50 and abs(p.dt - 0.02) < 1e-9
        pos = np.asarray(p.positions).reshape(p.steps, -1, 3)
        assert np.isfinite(pos).all()
        assert np.abs(pos[0, 42:] - demos[0].objects[k - 1]).max() < 0.2  # starts near the observed objects
        # Without its checkpoint the same service serves the naive baseline: other plans, not the network's.
        assert naive()[-1].dt == pytest.approx(0.1) and naive()[-1].steps == 11
        health = query_json(session, "xm/policy/other/@health")
        assert health and health[0]["status"] == "degraded" and "missing.pt" in health[0]["message"]
        assert "nan_plan" not in query_json(session, "xm/policy/main/@health")[0]["errors"]
    finally:
        learned.stop()
        fallback.stop()


def test_the_naive_fallback_replays_the_training_demonstrations_or_holds_the_hands(router, tmp_path):
    """method = "naive": the demonstrations `xm train` saved beside the checkpoint, replayed from
    the episode start; with none to replay the node holds the observed hands and says so."""
    endpoint, session = router
    demos = [generate_demo("assembly", s, index=i) for i, s in enumerate((11, 12))]
    (tmp_path / "demos").mkdir()
    for i, d in enumerate(demos):
        d.save(tmp_path / "demos" / f"demo_{i}.npz")
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"policy": {
        "main": {"method": "naive", "checkpoint": str(tmp_path / "policy.pt"), "rate_hz": 5.0},
        "hold": {"method": "naive", "demos": str(tmp_path / "none"), "rate_hz": 5.0}}})
    naive = ServiceProcess("policy", dep, "main", tmp_path / "naive.log")
    hold = ServiceProcess("policy", dep, "hold", tmp_path / "hold.log")
    try:
        plans, _a = collect(session, "xm/policy/*/plan", "xm_msgs/msg/Plan")
        assert wait_for(lambda: query_json(session, "xm/policy/hold/@health"), 60), hold.output()
        assert wait_for(lambda: query_json(session, "xm/policy/main/@health"), 60), naive.output()
        session.put("xm/world/sim/session", msgs.serialize(msgs.make(
            "xm_msgs/msg/Session", header=msgs.header(time.time()), task="assembly", demo=0, phase="reach",
            tactile_hand="left", seed_layout="{}")))
        deadline = time.time() + 20
        while time.time() < deadline and not ({"naive", "hold"} <= {p.policy for p in plans}):
            session.put("xm/recon/main/scene", _scene_msg(demos[1], 0, time.time(), hide=8))
            time.sleep(0.1)
        replay = [p for p in plans if p.policy == "naive"]
        held = [p for p in plans if p.policy == "hold"]
        assert replay and held, (naive.output(), hold.output())
        pos = np.asarray(replay[0].positions).reshape(replay[0].steps, 42, 3)
        assert np.abs(pos[0] - demos[1].hands[0].reshape(42, 3)).max() < 0.05  # the nearest start: demo 1
        assert np.abs(pos[-1] - pos[0]).max() > 1e-3  # ... replayed: its hands move over the horizon
        still = np.asarray(held[0].positions).reshape(held[0].steps, 42, 3)
        seen = np.asarray(held[0].mask).reshape(held[0].steps, 42).astype(bool)
        np.testing.assert_allclose(still[-1][seen[-1]], demos[1].hands[0].reshape(42, 3)[seen[-1]], atol=1e-6)
        assert not seen[:, 8].any() and seen[:, 7].all()  # the hidden point carries no goal
        health = query_json(session, "xm/policy/hold/@health")[0]
        assert health["status"] == "degraded" and "holding the observed hands" in health["message"]
    finally:
        naive.stop()
        hold.stop()

