"""A standby camhub (services/camhub/service.py ``prepare``): the simulated rig's renderer is
built and has drawn a frame before the spare takes over, on the thread that renders with it."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import pytest

from services.camhub import service as camhub
from services.camhub.driver import SNAPSHOT_KEY
from services.world import render
from shared.config import load_deployment
from shared.keys import CAMERAS
from tests.conftest import write_deployment


class FakeNode:
    """What CamhubService uses of a Node; its session answers the world's snapshot query."""

    def __init__(self, snapshot: render.Snapshot) -> None:
        reply = SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: snapshot.to_json())))
        self.session = SimpleNamespace(get=lambda key, timeout: [reply] if key == SNAPSHOT_KEY else [])
        self.log = logging.getLogger("test-camhub")
        self.status, self.message, self.health_extra = "starting", "", None

    def output(self, port: str, camera: str) -> SimpleNamespace:
        return SimpleNamespace(put=lambda msg: None)

    def input(self, port: str, handler) -> None:
        pass

    def set_status(self, status: str, message: str = "") -> None:
        self.status, self.message = status, message


@pytest.fixture
def built(monkeypatch) -> list[tuple]:
    """The arguments of every SceneRenderer built from here on."""
    built = []
    real = render.SceneRenderer

    def counting(*args, **kwargs):
        built.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(render, "SceneRenderer", counting)
    return built


def test_a_spare_renders_its_first_frame_with_the_renderer_it_prepared(tmp_path, built):
    probe = render.SceneRenderer("assembly", 64, 48)  # a snapshot of the task's initial state
    snap = render.snapshot("assembly", probe.data)
    probe.close()
    built.clear()
    dep = load_deployment(write_deployment(tmp_path / "d.toml", "tcp/127.0.0.1:7999", {
        "world": {"sim": {"task": "assembly"}}, "camhub": {"main": {"width": 64, "height": 48}}}))
    params = dep.service_params(camhub.CamhubService.Params, "camhub", "main")
    camhub.CamhubService.prepare(params, deployment=dep)
    assert built == [("assembly", 64, 48)], "prepare builds the world's task at the rig's size"

    service = camhub.CamhubService(FakeNode(snap), params)
    frames = service.worker.submit(service.rig.trigger, service.windows, 0.0).result()
    assert [f.name for f in frames.frames] == list(CAMERAS) and frames.frames[0].image.shape == (48, 64, 3)
    assert len(built) == 1, "the takeover's first frame built a renderer of its own"
    service.worker.submit(service.rig.close).result()

    again = camhub.CamhubService(FakeNode(snap), params)  # nothing prepared for it: built at its first frame
    again.worker.submit(again.rig.trigger, again.windows, 0.0).result()
    assert len(built) == 2
    again.worker.submit(again.rig.close).result()
