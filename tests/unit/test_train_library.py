"""`xm train RECORDINGS_DIR`: the demonstration library's splits, exclusions and trims decide what
is learned from (learning/from_library.py)."""

from __future__ import annotations

import json

import pytest

from learning.cli import train_main
from learning.from_library import library_data
from services.panel.library import DemoMeta, write_meta
from tests.unit.panel_recordings import write_demo


@pytest.fixture()
def library(tmp_path):
    """Three 2 s recordings: a trimmed train one, a validation one, an excluded one, and a cut one."""
    for name, meta in (("a", DemoMeta(label="first", split="train", trim_start_s=0.5, trim_end_s=1.5)),
                       ("b", DemoMeta(label="second", split="validation")),
                       ("c", DemoMeta(label="third", split="excluded"))):
        write_demo(tmp_path / f"{name}.mcap", keys=("scene", "session"))
        write_meta(tmp_path / f"{name}.mcap", meta)
    write_demo(tmp_path / "d.mcap", keys=("scene", "session"), close=False)
    return tmp_path


def test_splits_exclusions_and_trims_come_from_the_sidecars(library):
    data = library_data(library)
    assert [d.meta["recording"] for d in data.train] == ["a"]
    assert [d.meta["recording"] for d in data.validation] == ["b"]
    # the trim keeps the scenes of 0.5-1.5 s: 1 s at 0.02 s steps, not the whole 2 s
    assert 45 <= data.train[0].steps <= 52
    assert data.validation[0].steps >= 98
    assert [u["name"] for u in data.used] == ["a", "b"]
    assert data.used[0]["trim_s"] == [0.5, 1.5]
    assert any(r.startswith("c: excluded") for r in data.report)
    assert any(r.startswith("d: not trainable: cut by a crash") for r in data.report)


def test_xm_train_on_a_directory_trains_on_the_library(library, tmp_path_factory, capsys):
    out = tmp_path_factory.mktemp("model")
    progress = out / "progress.jsonl"
    assert train_main([str(library), "--preset", "single_state", "--steps", "2", "--set", "hidden=32,32",
                       "--set", "batch=8", "--threads", "1", "--out", str(out), "--progress", str(progress)]) == 0
    info = json.loads((out / "train.json").read_text())
    assert (info["train_demos"], info["selection_demos"]) == (1, 1)
    assert [u["name"] for u in info["data"]] == ["a", "b"]
    records = [json.loads(line) for line in progress.read_text().splitlines()]
    assert records[-1]["step"] == 2 and any("eval" in r for r in records) and any("loss" in r for r in records)
    assert "c: excluded" in capsys.readouterr().err


def test_a_library_without_training_demonstrations_is_refused(library, tmp_path, capsys):
    write_meta(library / "a.mcap", DemoMeta(split="validation"))
    assert train_main([str(library), "--steps", "2", "--out", str(tmp_path / "m")]) == 2
    assert "no training demonstrations in the library" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
    assert train_main([str(library), "--val", "1", "--out", str(tmp_path / "m")]) == 2
