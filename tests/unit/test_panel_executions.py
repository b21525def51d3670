"""Executions from the dashboard (services/panel/executions.py): the sequence of world commands, the
refusals, STOP, the outcome log beside the model and its summary in the model list."""

from __future__ import annotations

import json
import threading

import pytest

from services.panel import executions
from services.panel.executions import Execution, ExecutionError, Runner, outcome_fields
from services.panel.jobs import models, models_table
from tests.conftest import wait_until


class World:
    """Stands in for the world's @cmd queryables; ``outcome`` is its success test's reply."""

    def __init__(self, outcome: dict | None = None, answers: bool = True) -> None:
        self.calls: list[tuple[str, dict]] = []
        self.outcome = outcome or {"ok": True, "task": "assembly", "mode": "robot", "sim_time": 12.0,
                                   "success": True, "seated": True, "connector_gap_mm": 1.234}
        self.answers = answers

    def __call__(self, key: str, request: dict) -> list[dict]:
        verb = key.rsplit("/", 1)[-1]
        assert key.startswith("xm/world/sim/@cmd/")
        self.calls.append((verb, request))
        if not self.answers:
            return []
        return [self.outcome] if verb == "outcome" else [{"ok": True}]


def test_an_execution_resets_runs_in_robot_mode_and_logs_the_world_s_test():
    world = World()
    done = Runner(world).run(3, 0.05, True, "/models/m1/policy.pt", "learned",
                             {"session": "s1", "teacher": "ada", "task": "assembly"})
    assert [v for v, _ in world.calls] == ["reset", "mode", "outcome", "mode"]
    assert world.calls[0][1] == {"seed": 3} and world.calls[1][1] == {"mode": "robot"}
    assert world.calls[3][1] == {"mode": "teacher"}  # the cell goes back to demonstrating
    assert done.success and not done.stopped and done.seed == 3 and done.seconds >= 0.05
    assert done.distances == {"connector_gap_mm": 1.23} and done.checks == {"seated": True}
    assert (done.session, done.teacher, done.task, done.checkpoint) == ("s1", "ada", "assembly", "/models/m1/policy.pt")


def test_the_robot_never_moves_unless_armed_and_bad_requests_are_refused():
    world = World()
    runner = Runner(world)
    with pytest.raises(ExecutionError, match="not armed"):
        runner.run(0, 1.0, False, None, "naive")
    with pytest.raises(ExecutionError, match="does not answer"):
        runner.run(0, 1.0, None, None, "naive")
    with pytest.raises(ExecutionError, match="seconds must be"):
        runner.run(0, 0.0, True, None, "naive")
    assert world.calls == []  # nothing was asked of the world
    with pytest.raises(ExecutionError, match="the world did not answer @cmd/reset"):
        Runner(World(answers=False)).run(0, 1.0, True, None, "naive")


def test_stop_ends_an_execution_early_and_a_second_one_is_refused_meanwhile():
    world = World()
    runner = Runner(world)
    started, result = threading.Event(), []
    thread = threading.Thread(target=lambda: result.append(runner.run(0, 60.0, True, None, "naive",
                                                                      on_started=started.set)))
    thread.start()
    assert started.wait(10)
    with pytest.raises(ExecutionError, match="an execution is running"):  # another browser's press
        runner.run(1, 1.0, True, None, "naive")
    runner.stop.set()  # STOP
    thread.join(10)
    [done] = result
    assert done.stopped and not done.success and done.seconds < 30  # a stopped execution is no success
    assert [v for v, _ in world.calls] == ["reset", "mode", "outcome", "mode"]
    assert not runner.running


def test_a_stop_handled_before_its_execution_starts_still_ends_it():
    """On a loaded host the page delivers Run and STOP together: STOP's handler may run first, and
    the execution clears ``stop`` as it starts; the robot STOP disarmed ends it all the same."""
    world = World()
    runner = Runner(world)
    runner.stop.set()  # STOP, handled before the execution's thread starts: the robot is disarmed
    done = runner.run(0, 60.0, True, None, "naive", armed_now=lambda: False)
    assert done.stopped and not done.success and done.seconds < 30
    later = runner.run(0, 0.2, True, None, "naive", armed_now=lambda: True)  # an older STOP ends no later run
    assert not later.stopped


def test_an_execution_ends_when_the_robot_reads_disarmed_whatever_order_the_presses_were_handled_in():
    """A disarm from any browser ends it, as does the disarm of a STOP handled in any order."""
    runner = Runner(World())
    armed = [True]
    done: list = []
    thread = threading.Thread(target=lambda: done.append(
        runner.run(0, 60.0, True, None, "naive", armed_now=lambda: armed[0])))
    thread.start()
    wait_until(lambda: runner.running and runner.started is not None, 10, "the execution running")
    armed[0] = False  # the hold's reply: disarmed
    thread.join(10)
    assert done and done[0].stopped and done[0].seconds < 30


def test_a_broken_outcome_is_an_error_and_the_world_still_returns_to_teacher_mode():
    world = World(outcome={"ok": False, "error": "no such command"})
    with pytest.raises(ExecutionError, match="no such command"):
        Runner(world).run(0, 0.01, True, None, "naive")
    assert world.calls[-1] == ("mode", {"mode": "teacher"})
    with pytest.raises(ExecutionError, match="did not answer"):
        outcome_fields({"ok": True, "success": "yes"})  # not a boolean
    ok, distances, checks = outcome_fields({"ok": True, "success": False, "coverage": 0.4, "checked": False,
                                            "offset_mm": float("nan")})
    assert not ok and distances == {"coverage": 0.4} and checks == {"checked": False}  # NaN left out


def test_the_log_beside_a_model_is_summarized_in_the_model_list(tmp_path):
    model = tmp_path / "models" / "20260101-000000-no_tactile"
    model.mkdir(parents=True)
    (model / "policy.pt").write_bytes(b"x")
    (model / "train.json").write_text(json.dumps({"preset": "no_tactile", "train_demos": 2, "selection_demos": 1}))
    log = executions.log_path(model / "policy.pt")
    assert log == model / "executions.jsonl"
    for success in (True, False, True):
        executions.append(log, Execution(str(model / "policy.pt"), "learned", 0, 9.0, success,
                                         {"connector_gap_mm": 1.5}, time="2026-01-01 10:00:00"))
    with log.open("a") as f:
        f.write("not json\n")  # a damaged line is skipped and counted
    read, bad = executions.read(log)
    assert [e.success for e in read] == [True, False, True] and bad == 1
    [m] = models(tmp_path / "models")
    assert m.executions == "2 / 3 succeeded"
    assert "| 2 / 3 succeeded |" in models_table([m])
    line = executions.describe(read[0])
    assert "**success**" in line and "connector gap 1.5 mm" in line and model.name in line


def test_a_long_wait_is_interrupted_promptly():
    runner = Runner(World())
    done: list[Execution] = []
    t = threading.Thread(target=lambda: done.append(runner.run(0, 120.0, True, None, "naive",
                                                                on_started=runner.stop.set)))
    t.start()
    wait_until(lambda: done, 20, "the stopped execution's outcome")
    assert done[0].stopped
