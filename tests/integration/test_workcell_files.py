"""deploy/workcell.toml without its serial devices (robot, gloves) and with the camera rig on
`files` sources: video files and image folders rendered by the simulator, as a recorded session
would be replayed. Every camera must publish its images and CameraInfo from the calibration file."""

from __future__ import annotations

import tomllib

import cv2
import numpy as np
import pytest

from services.world.render import SceneRenderer, snapshot
from services.world.sim import WorldSim
from shared import calibration, keys
from tests.conftest import ROOT, free_endpoint, free_port, query_router, wait_until, write_deployment, xm_up

pytestmark = pytest.mark.slow
FRAME_SETS = 4


def record_session(tmp, width: int, height: int) -> list[str]:
    """Render a few frame sets of the simulated teacher; cameras 0-2 as image folders, 3-4 as AVI
    (MJPG), 5-6 as MP4: the forms a recorded session comes in."""
    sim = WorldSim("assembly", seed=3)
    renderer = SceneRenderer("assembly", width, height)
    sets = []
    for _ in range(FRAME_SETS):
        sim.step(150)
        sets.append(renderer.render(snapshot(sim.task, sim.data, sim.robot_name, 3, sim.demo,
                                             sim.teacher.tactile_hand)))
    renderer.close()
    paths = []
    for c, cam in enumerate(renderer.cameras):
        frames = [cv2.cvtColor(s[c], cv2.COLOR_RGB2BGR) for s in sets]
        if c < 3:
            folder = tmp / cam.name
            folder.mkdir()
            for i, bgr in enumerate(frames):
                cv2.imwrite(str(folder / f"{i:05d}.png"), bgr)
            paths.append(str(folder))
            continue
        path, fourcc = (tmp / f"{cam.name}.avi", "MJPG") if c < 5 else (tmp / f"{cam.name}.mp4", "mp4v")
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 5.0, (width, height))
        assert writer.isOpened(), f"OpenCV cannot write {path.suffix}"
        for bgr in frames:
            writer.write(bgr)
        writer.release()
        paths.append(str(path))
    rig = calibration.RigCalibration([calibration.CameraCalibration(c.name, width, height, c.K, np.zeros(5),
                                                                    c.world_T_cam, 0.0) for c in renderer.cameras])
    calibration.save(rig, tmp / "rig.json")
    return paths


def test_workcell_deployment_runs_its_cameras_from_recorded_files(tmp_path):
    spec = tomllib.loads((ROOT / "deploy/workcell.toml").read_text())
    services = spec["services"]
    for device_service in ("robot", "glove"):  # serial devices this machine does not have
        services.pop(device_service)
    cam = services["camhub"]["main"]
    assert cam["source"] == "v4l2", "the workcell starts on real devices"
    cam.pop("devices")
    cam.update(source="files", files=record_session(tmp_path, cam["width"], cam["height"]),
               calibration=str(tmp_path / "rig.json"),
               rate_hz=5.0)  # 30 Hz of 640x480 JPEG is more than a shared 2-core test machine should spend
    services["panel"]["main"]["port"] = free_port()
    services["recorder"]["main"]["directory"] = str(tmp_path / "recordings")
    router = free_endpoint()
    deployment = write_deployment(tmp_path / "workcell.toml", router, services, clock=spec["deployment"]["clock"])
    camera_keys = {s.key for s in keys.REGISTRY if s.service == "camhub"}

    def up() -> list[dict] | None:
        """The health reports once every camera publishes and every service answers."""
        reports = query_router(router, "xm/**/@health")
        published = {k for r in reports for k, hz in r.get("published_hz", {}).items() if hz > 0}
        return reports if camera_keys <= published and set(services) <= {r["service"] for r in reports} else None

    with xm_up(deployment, tmp_path / "up.log"):
        reports = wait_until(up, 120, lambda: f"every camera publishing and every service answering @health; "
                             f"log: {(tmp_path / 'up.log').read_text()[-3000:]}", period=2.0)
        camhub = next(r for r in reports if r["service"] == "camhub")
        assert camhub["source"] == "files" and camhub["intrinsics"] == f"calibration {tmp_path / 'rig.json'}"
        assert all(c["status"] == "ok" for c in camhub["cameras"].values()), camhub["cameras"]
