"""Training jobs of the dashboard (services/panel/jobs.py): a real `xm train` process on a small
library with a tiny budget; its progress, the model that appears whole on success, cancel leaving
nothing, refusals."""

from __future__ import annotations

import threading

import pytest

from services.panel.execute import rejections_text
from services.panel.jobs import JobBusyError, JobError, Trainer, check_library, models, models_table
from services.panel.learn import checkpoint_problem
from services.panel.library import DemoMeta, Library, write_meta
from shared.realtime import autogroup_nice
from tests.conftest import wait_until
from tests.unit.panel_recordings import write_demo

TINY = "--set hidden=32,32 --set batch=8 --preset single_state"


@pytest.fixture()
def library(tmp_path):
    rec = tmp_path / "recordings"
    rec.mkdir()
    for name, split in (("a", "train"), ("b", "validation")):
        write_demo(rec / f"{name}.mcap", keys=("scene", "session"))
        write_meta(rec / f"{name}.mcap", DemoMeta(label=name, split=split))
    return rec


def test_nothing_to_train_on_is_refused_with_the_reason(library):
    assert check_library(Library(library).scan()) == (1, 1)
    write_meta(library / "a.mcap", DemoMeta(split="validation"))
    with pytest.raises(JobError, match=r"only validation demonstrations \(2\)"):
        check_library(Library(library).scan())
    with pytest.raises(JobError, match="no usable demonstrations"):
        check_library([])


def test_a_job_reports_progress_and_leaves_a_whole_model(library, tmp_path):
    trainer = Trainer(tmp_path / "models", TINY, threads=1)
    with pytest.raises(JobError, match="unknown preset"):
        trainer.start(library, "best")
    job = trainer.start(library, "single_state", steps=3)
    with pytest.raises(JobBusyError, match="a training job is running"):  # a second press is told
        trainer.start(library, "single_state", steps=3)
    assert job.partial.is_dir() and not job.final.exists() and models(trainer.models) == []
    wait_until(lambda: trainer.poll().state != "running", 300, lambda: (job.partial / "train.log").read_text())
    assert job.state == "done", job.message
    assert not job.partial.exists() and (job.final / "policy.pt").is_file()
    assert job.progress.step == 3 and job.progress.loss and job.progress.evals
    [model] = models(trainer.models)
    assert (model.name, model.preset, model.train_demos, model.validation_demos) == (job.name, "single_state", 1, 1)
    assert model.data == ["a (train)", "b (validation)"] and model.score_mm is not None
    assert job.name in models_table([model], str(model.checkpoint))


def test_cancel_stops_the_job_and_leaves_no_model(library, tmp_path):
    trainer = Trainer(tmp_path / "models", TINY, threads=1)
    job = trainer.start(library, "single_state", steps=1_000_000)
    wait_until(lambda: trainer.poll().progress.steps, 300, lambda: (job.partial / "train.log").read_text())
    assert trainer.cancel() and job.state == "cancelled"
    assert job.process.poll() is not None and not job.partial.exists() and not job.final.exists()
    assert list((tmp_path / "models").iterdir()) == []
    assert not trainer.cancel()  # nothing left to cancel


def test_a_job_runs_in_a_session_whose_cpu_share_is_set_apart_from_the_services(library, tmp_path):
    # a smaller share (nice up) is permitted without privileges; the panel's default asks for a larger one
    trainer = Trainer(tmp_path / "models", TINY, threads=1, share_steps=-3)
    job = trainer.start(library, "single_state", steps=1_000_000)
    try:
        if autogroup_nice(job.process.pid) is None:
            pytest.skip("this kernel has no autogroups")
        assert job.cpu_share == 3 == autogroup_nice(job.process.pid)  # a new session starts at nice 0
    finally:
        trainer.cancel()


def test_a_failing_job_says_why_and_a_killed_panel_leaves_nothing_listed(library, tmp_path):
    (tmp_path / "models" / ".old.partial").mkdir(parents=True)  # a panel killed mid-job
    trainer = Trainer(tmp_path / "models", TINY + " --set steps=many", threads=1)
    assert not (tmp_path / "models" / ".old.partial").exists()
    job = trainer.start(library, "single_state")
    wait_until(lambda: trainer.poll().state != "running", 300, "the job to fail")
    assert job.state == "failed" and "exit code 2" in job.message and "steps" in job.message
    assert list((tmp_path / "models").iterdir()) == []


def test_a_restarted_panel_stops_the_job_its_predecessor_left_running(library, tmp_path):
    first = Trainer(tmp_path / "models", TINY, threads=1)
    job = first.start(library, "single_state", steps=1_000_000)
    Trainer(tmp_path / "models", TINY, threads=1)  # the panel killed and started again
    wait_until(lambda: job.process.poll() is not None, 30, "the orphaned job stopped")
    assert list((tmp_path / "models").iterdir()) == []


def test_rejections_on_the_way_to_the_robot_are_named():
    assert rejections_text(None, None) == "rejections: none"
    text = rejections_text({"errors": {"solve_rejected": 3}, "last_rejection": {"reason": "collision", "status": 2},
                            "last_plan_rejection": "NaN in the plan"},
                           {"errors": {"ignored_disarmed": 5}, "rejections": {"non-finite sample": 1}})
    assert text == ("rejections: trajopt rejected 3 solves (last: collision); trajopt rejected a plan: NaN in the "
                    "plan; robot rejected 1 trajectories: non-finite sample; robot ignored 5 trajectories while "
                    "disarmed")


def test_a_job_dies_with_the_thread_that_started_it(library, tmp_path):
    """As with a killed panel: the job's process does not outlive its starter."""
    trainer = Trainer(tmp_path / "models", TINY, threads=1)
    started: list = []
    starter = threading.Thread(target=lambda: started.append(trainer.start(library, "single_state", steps=1_000_000)))
    starter.start()
    starter.join()
    wait_until(lambda: started[0].process.poll() is not None, 30, "the job to die with its starter")


def test_the_first_network_is_trained_in_place_demonstrations_first(library, tmp_path):
    trainer = Trainer(tmp_path / "models", "--set hidden=32,32 --set batch=8 --steps 3", threads=1)
    checkpoint = tmp_path / "policy" / "policy.pt"
    with pytest.raises(JobError, match="writes policy.pt"):
        trainer.start_first(tmp_path / "policy" / "net.pt", "single_state")
    with pytest.raises(JobError, match="steps must be >= 0"):
        trainer.start_first(checkpoint, "single_state", steps=-1)
    job = trainer.start_first(checkpoint, "single_state", steps=4000)
    cmd = list(job.process.args)  # the first network's own budget; the extra args (a tiny one here) come after
    assert cmd[cmd.index("--teacher"):cmd.index("--teacher") + 6] == ["--teacher", "0", "--out", str(checkpoint.parent),
                                                                      "--steps", "4000"]
    with pytest.raises(JobBusyError, match="a training job is running"):  # the page's Train waits for it
        trainer.start(library, "single_state", steps=3)
    wait_until(lambda: trainer.poll().state != "running", 300, lambda: (job.partial / "train.log").read_text())
    assert job.state == "done", job.message
    assert checkpoint.is_file() and not job.partial.exists()
    assert len(list((checkpoint.parent / "demos").glob("*.npz"))) == 3
    assert job.progress.step == 3 and models(trainer.models) == []  # not one of the library's models
    assert checkpoint_problem(checkpoint) == ""  # loads: a restarted panel trains nothing
    assert "is missing" in checkpoint_problem(tmp_path / "none.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    assert "does not load" in checkpoint_problem(tmp_path / "junk.pt")


def test_a_cancelled_first_network_leaves_no_checkpoint(library, tmp_path):
    trainer = Trainer(tmp_path / "models", "--set hidden=32,32 --set batch=8 --steps 1000000", threads=1)
    checkpoint = tmp_path / "policy" / "policy.pt"
    job = trainer.start_first(checkpoint, "single_state")
    wait_until(lambda: trainer.poll().progress.steps, 300, lambda: (job.partial / "train.log").read_text())
    assert trainer.cancel() and job.state == "cancelled"
    assert not checkpoint.exists() and not list(checkpoint.parent.glob("*.tmp"))
