"""A standby spare's preparation (shared/runtime/service.py ``prepare_spare``)."""

from __future__ import annotations

from dataclasses import dataclass

from shared.runtime.service import prepare_spare
from tests.conftest import write_deployment


class Prepared:
    seen: list = []

    @dataclass
    class Params:
        segment_s: float = 1.0

    @classmethod
    def prepare(cls, params: Params) -> None:
        if params.segment_s < 0:
            raise ValueError("segment_s must be >= 0")
        cls.seen.append(params)


def test_a_spare_prepares_with_its_instance_params_and_survives_a_failing_prepare(tmp_path, capsys):
    dep = write_deployment(tmp_path / "d.toml", "tcp/127.0.0.1:7999",
                           {"recorder": {"a": {"segment_s": 5.0}, "b": {"segment_s": -1.0}}})
    prepare_spare("recorder", Prepared, str(dep), "a")
    assert Prepared.seen == [Prepared.Params(segment_s=5.0)]
    prepare_spare("recorder", Prepared, str(dep), "b")  # reported, not raised: the real start reports it
    assert Prepared.seen == [Prepared.Params(segment_s=5.0)]
    assert "prepare failed" in capsys.readouterr().err
    prepare_spare("recorder", object, str(dep), "a")  # no prepare: nothing to do


class NeedsDeployment:
    seen: list = []

    @dataclass
    class Params:
        width: int = 64

    @classmethod
    def prepare(cls, params: Params, deployment=None) -> None:
        cls.seen.append((params, deployment.services["world"]["sim"]["task"]))


def test_a_prepare_that_declares_deployment_gets_the_loaded_deployment(tmp_path):
    dep = write_deployment(tmp_path / "d.toml", "tcp/127.0.0.1:7999",
                           {"world": {"sim": {"task": "pouring"}}, "camhub": {"main": {"width": 32}}})
    prepare_spare("camhub", NeedsDeployment, str(dep), "main")
    assert NeedsDeployment.seen == [(NeedsDeployment.Params(width=32), "pouring")]
