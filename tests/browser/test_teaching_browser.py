"""The teaching folders in a real browser: headless Chromium (DevTools protocol, mouse and input
events dispatched in the page) starts a teaching session, records two demonstrations through a
stand-in recorder that writes real MCAP files, labels one for validation in the library, reviews a
third with the scrubber (the rendered scene changes with its position), plays, pauses, steps it
and trims its start; then trains on the library (a second Train is told a job runs, Cancel leaves
no model, a tiny budget leaves one in the model list), serves it, runs a neural simulation of it
from the reviewed demonstration (the ghost drawn over the scene), arms the robot, draws the
optimizer's trajectory (the rendered scene changes), runs an execution whose outcome is logged
beside the model and shown in the model list and the session line (a second press meanwhile is
told one runs), and stops the robot, against stand-ins for the policy, robot, trajopt and world
services (the stand-in's rollout is the policy's own simulation code on the trained checkpoint).
Screenshots: .cache/teaching_*.png. The live overview's neural simulation against the real policy
service and its alerts as toasts: test_overview_browser.py."""

from __future__ import annotations

import json
import re
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.policy.simulation import Simulator, scene_from_request
from shared import msgs
from shared.kinematics import load_robot
from tests.browser._cdp import Chromium, find_chromium
from tests.browser._page import PATIENCE_S, WAIT, choose, click_button, key, page_text, type_into, value_of, viewport
from tests.conftest import ROOT, ServiceProcess, free_port, query_json, wait_for, wait_until, write_deployment
from tests.unit.panel_recordings import write_demo

CHROMIUM = find_chromium()
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="needs /usr/bin/chromium (apt-get install chromium)")]


def world_session() -> object:
    return msgs.make("xm_msgs/msg/Session", header=msgs.header(time.time()), task="pick_place", demo=0,
                     phase="approach", tactile_hand="right", seed_layout='{"cup": [0.1, 0.0]}')


def sidecar(path: Path) -> dict:
    return json.loads(path.with_name(path.name[:-len(".mcap")] + ".demo.json").read_text())


@pytest.mark.timeout(900)  # 2 min on an idle host; software WebGL and a training job beside a busy cell take minutes
def test_teaching_session_library_and_review_in_headless_chromium(router, tmp_path):
    endpoint, session = router
    rec_dir = tmp_path / "recordings"
    rec_dir.mkdir()
    write_demo(rec_dir / "earlier.mcap", seconds=4.0, masked=(1.0, 2.0), lost=(2.5, 7))
    port = free_port()
    models_dir = tmp_path / "models"
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"panel": {"main": {
        "port": port, "fps": 10.0, "health_period_s": 2.0, "recordings": str(rec_dir), "models": str(models_dir),
        "train_threads": 1, "train_args": "--set hidden=32,32 --set batch=8"}}})
    requests: list[tuple[str, dict]] = []

    def fake_recorder(query) -> None:  # stands in for the recorder service: stop writes a real MCAP
        verb = str(query.key_expr).rsplit("/", 1)[-1]
        payload = query.payload.to_bytes() if query.payload is not None else b""
        req = json.loads(payload or b"{}")
        requests.append((verb, req))
        path = Path(next(r for v, r in reversed(requests) if v == "start")["path"])
        if verb == "stop":
            write_demo(path, seconds=1.0)
        query.reply(str(query.key_expr), json.dumps({"ok": True, "path": str(path), "messages": {"k": 1},
                                                     "bytes": 1000}))

    queryables = [session.declare_queryable(f"xm/recorder/main/@cmd/{v}", fake_recorder) for v in ("start", "stop")]
    queryables += stand_in_robot_and_policy(session, requests)
    queryables += stand_in_world(session, requests)
    pub = session.declare_publisher("xm/world/sim/session")
    stop = threading.Event()

    def feed() -> None:  # the world's label at 2 Hz, stamped now
        while not stop.wait(0.5):
            pub.put(msgs.serialize(world_session()))

    feeder = threading.Thread(target=feed, daemon=True)
    panel = ServiceProcess("panel", dep, "main", tmp_path / "panel.log")
    browser = None
    cache = ROOT / ".cache"
    cache.mkdir(exist_ok=True)
    try:
        feeder.start()
        assert wait_for(lambda: query_json(session, "xm/panel/main/@health"), 90), panel.output()
        browser = Chromium(CHROMIUM, tmp_path / "profile", size=(1024, 800))  # fewer pixels to rasterize
        browser.navigate(f"http://127.0.0.1:{port}")
        wait_until(lambda: "earlier" in page_text(browser), WAIT, lambda: "the library listing the "
                   f"recording already there; page: {page_text(browser)[:800]}", period=0.5)

        # 1. a teaching session: the task comes from the world's label, the teacher is typed
        wait_until(lambda: value_of(browser, "task") == "pick_place", WAIT, "the task filled from the world's session")
        type_into(browser, "teacher", "ada")
        wait_until(lambda: value_of(browser, "teacher") == "ada", WAIT, "the typed teacher")
        choose(browser, "glove hand", "left")
        click_button(browser, "Start session")  # at once: the press follows the typed and chosen values
        wait_until(lambda: "teacher ada, glove on the left hand, 0 demonstrations" in page_text(browser), WAIT,
                   lambda: f"the session line; page: {page_text(browser)[:800]}", period=0.3)

        # 2. two demonstrations, each one recording with a label, layout and outcome
        demos = []
        for label, outcome in (("first grasp", "success"), ("second grasp", "failure")):
            type_into(browser, "next label", label)
            n = len(requests)
            click_button(browser, "Start recording")
            wait_until(lambda n=n: len(requests) > n, WAIT, "the start query")
            verb, req = requests[-1]
            assert verb == "start" and req["keys"] == "xm/**" and Path(req["path"]).parent == rec_dir.resolve()
            assert Path(req["path"]).name.startswith("pick_place-ada-")
            wait_until(lambda: "recording to" in page_text(browser), WAIT, "the recorder's reply shown")
            click_button(browser, outcome)
            path = Path(req["path"])
            wait_until(lambda p=path, o=outcome: p.exists() and sidecar(p)["outcome"] == o, WAIT,
                       f"{outcome} stored beside {path.name}")
            meta = sidecar(path)
            assert (meta["label"], meta["task"], meta["teacher"], meta["glove_hand"], meta["split"]) == \
                (label, "pick_place", "ada", "left", "train")
            assert meta["layout"] == '{"cup": [0.1, 0.0]}'  # the world's seed layout
            demos.append(path)
        wait_until(lambda: "second grasp" in page_text(browser), WAIT, "the library listing both")
        browser.screenshot(cache / "teaching_session.png", PATIENCE_S)

        # 3. the library: the first demonstration becomes validation data
        choose(browser, "demonstration", demos[0].name[:-len(".mcap")])
        wait_until(lambda: value_of(browser, "label") == "first grasp", WAIT, "the picked demonstration's label")
        choose(browser, "split", "validation")
        click_button(browser, "Save")
        wait_until(lambda: sidecar(demos[0])["split"] == "validation", WAIT, "the split saved in the sidecar")
        assert sidecar(demos[1])["split"] == "train"
        wait_until(lambda: "2 for training, 1 for validation" in page_text(browser), WAIT,
                   lambda: f"the library's counts; page: {page_text(browser)[-1500:]}")
        browser.screenshot(cache / "teaching_library.png", PATIENCE_S)

        # 4. review: the scrubber moves the replayed scene
        choose(browser, "demonstration", "earlier")
        click_button(browser, "Review")
        wait_until(lambda: "reviewing earlier" in page_text(browser), WAIT, "the review opened")
        text = page_text(browser)
        assert "keypoints unobserved in 20 of 81 scenes" in text and "right glove lost 7 frames" in text, text[-1500:]
        wait_until(lambda: browser.evaluate("document.querySelectorAll('.uplot canvas').length", PATIENCE_S) >= 1, WAIT,
                   "the signals plot")
        before = wait_until(lambda: (s := browser.screenshot(tmp_path / "a.png", PATIENCE_S)) and
                            viewport(s).std() > 5 and s, WAIT, "a drawn 3D view")
        before_px = viewport(before)
        key(browser, "time", "End")  # the scrubber to the end: 4 s, the hands 0.2 m further along x
        wait_until(lambda: float(value_of(browser, "time") or 0) > 3.0, WAIT,
                   lambda: f"the slider at the end (shows {value_of(browser, 'time')})")
        wait_until(lambda: (query_json(session, "xm/panel/main/@health")[0]["reviewing"] or {}).get("at_s", 0) > 3.0,
                   WAIT, lambda: f"the panel's playhead at the end ({query_json(session, 'xm/panel/main/@health')})")

        def moved():
            shot = browser.screenshot(tmp_path / "b.png", PATIENCE_S)
            return shot if np.abs(viewport(shot) - before_px).sum(axis=2).__gt__(60).mean() > 0.002 else None

        shot = wait_until(moved, WAIT, "the 3D view changed by the scrubber", period=0.5)
        shutil.copy(shot, cache / "teaching_review.png")

        # 5. play from the start of the kept part, pause, trim
        key(browser, "time", "Home")
        wait_until(lambda: float(value_of(browser, "time") or 9) < 1.0, WAIT, "the slider back at the start")
        click_button(browser, "play")
        wait_until(lambda: float(value_of(browser, "time") or 0) > 1.5, WAIT, "the slider moving while playing")
        click_button(browser, "pause")

        def review() -> dict:
            return query_json(session, "xm/panel/main/@health")[0]["reviewing"]

        paused = wait_until(lambda: (r := review()) and not r["playing"] and r, WAIT, "paused")
        click_button(browser, "<")  # one scene back (scenes every 0.05 s; playing may have reached the end)
        stepped = wait_until(lambda: (r := review())["at_s"] != paused["at_s"] and r, WAIT, "a step")
        assert 0.0 < paused["at_s"] - stepped["at_s"] <= 0.051 and stepped["name"] == "earlier"
        click_button(browser, "start here")
        earlier = rec_dir / "earlier.mcap"
        trimmed = wait_until(lambda: sidecar(earlier)["trim_start_s"] if (earlier.with_name("earlier.demo.json")
                                                                          .exists()) else None, WAIT, "a stored trim")
        assert 1.0 < trimmed < 4.0
        wait_until(lambda: "the file is unchanged" in page_text(browser), WAIT, "the trim confirmed")
        learn_and_execute(browser, session, models_dir, requests, tmp_path)
        browser.screenshot(cache / "teaching_execute.png", PATIENCE_S)
        text = " ".join(page_text(browser).split())
        missing = [name for name in walkthrough_names() if name not in text]
        assert not missing, f"named in the README's walkthrough, not on the page: {missing}"
        health = query_json(session, "xm/panel/main/@health")[0]
        assert not {k for k in health["errors"] if k.startswith(("draw_error", "library_error", "review_error",
                                                                 "train_monitor_error", "execute_error",
                                                                 "neural_sim_error"))}, \
            health["errors"]
    finally:
        stop.set()
        feeder.join(5)
        if browser is not None:
            browser.close()
        for q in queryables:
            q.undeclare()
        assert panel.stop() in (0, -15), panel.output()


def walkthrough_names() -> list[str]:
    """The controls (bold) and fields (code) the README's walkthrough names; files and commands aside."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Teaching from the dashboard", 1)[1].split("\n## ", 1)[0]
    names = re.findall(r"\*\*([^*]+)\*\*", section) + re.findall(r"`([^`]+)`", section)
    names = [" ".join(n.split()) for n in names]
    assert len(names) > 20, "the walkthrough names the page's controls"
    return [n for n in names if "/" not in n and not n.startswith("make ")]


def stand_in_robot_and_policy(session, requests: list) -> list:
    """Queryables standing in for the robot service's arm gate and the policy's @cmd/serve (the real
    ones: tests/contract/test_robot_arm.py, test_policy_serve.py, test_policy_simulate.py); each
    request is appended to ``requests`` as (verb, request). Its @cmd/simulate rolls the served
    checkpoint out with the policy service's own code (services/policy/simulation.py)."""
    state = {"armed": False, "checkpoint": None}
    simulator = Simulator()

    def answer(key: str, query) -> None:  # key: the queryable's own (the query's may hold wildcards)
        verb = key.rsplit("/", 1)[-1]
        req = json.loads((query.payload.to_bytes() if query.payload is not None else b"") or b"{}")
        if verb == "@health":
            reply = ({"service": "robot", "instance": "workcell", "armed": state["armed"]} if "/robot/" in key else
                     {"service": "policy", "instance": "main", "method": "learned", "checkpoint": state["checkpoint"]})
        else:
            requests.append((verb, req))
            if verb == "arm":
                state["armed"] = bool(req["armed"])
            elif verb == "hold":
                state["armed"] = state["armed"] and not req.get("disarm")
            elif verb == "serve":
                state["checkpoint"] = req["checkpoint"]
            if verb == "simulate":
                try:
                    reply = simulator.rollout(Path(req.get("checkpoint") or state["checkpoint"]),
                                              scene_from_request(req["start"]), float(req["seconds"]))
                except (ValueError, KeyError, TypeError) as exc:
                    reply = {"ok": False, "error": str(exc)}
            else:
                reply = {"ok": True, "armed": state["armed"], "loading": req.get("checkpoint")}
        query.reply(key, json.dumps(reply))

    return [session.declare_queryable(k, lambda q, k=k: answer(k, q)) for k in (
        "xm/robot/workcell/@cmd/arm", "xm/robot/workcell/@cmd/hold", "xm/robot/workcell/@health",
        "xm/policy/main/@cmd/serve", "xm/policy/main/@cmd/simulate", "xm/policy/main/@health")]


def learn_and_execute(browser: Chromium, session, models_dir: Path, requests: list, tmp_path: Path) -> None:
    """6. train on the library from the page; 7. serve the model, simulate it, arm, stop."""
    choose(browser, "preset", "single_state")
    type_into(browser, "steps", "100000")  # a long job, to be cancelled
    wait_until(lambda: value_of(browser, "steps") == "100000", WAIT, "the typed budget")
    click_button(browser, "Train")
    wait_until(lambda: (query_json(session, "xm/panel/main/@health")[0]["training"] or {}).get("state") == "running",
               WAIT, "the job running")
    click_button(browser, "Train")  # a second press while the job runs is told so
    wait_until(lambda: "Train refused" in page_text(browser), WAIT, "the second Train refused")
    assert "a training job is running" in page_text(browser)
    click_button(browser, "Cancel training")
    wait_until(lambda: "cancelled; no model written" in page_text(browser), WAIT, "the job cancelled")
    assert not [p for p in models_dir.iterdir()]  # no model, no partial directory

    type_into(browser, "steps", "3")
    wait_until(lambda: value_of(browser, "steps") == "3", WAIT, "the tiny budget")
    click_button(browser, "Train")
    wait_until(lambda: " done: wrote " in page_text(browser), WAIT,  # its progress line, once the job is done
               lambda: f"the job done; page: {page_text(browser)[-1500:]}", period=0.5)
    [model] = [p for p in models_dir.iterdir()]
    assert (model / "policy.pt").is_file() and model.name.endswith("single_state")
    wait_until(lambda: browser.evaluate("document.querySelectorAll('.uplot canvas').length", PATIENCE_S) >= 2, WAIT,
               "the loss and validation plots")
    wait_until(lambda: f"{model.name}\tsingle_state\t" in page_text(browser), WAIT,
               lambda: f"the model in the model list; page: {page_text(browser)[-1500:]}")
    health = query_json(session, "xm/panel/main/@health")[0]
    assert health["training"]["state"] == "done" and health["models"] == 1
    browser.screenshot(ROOT / ".cache" / "teaching_learn.png", PATIENCE_S)

    choose(browser, "model", model.name)
    click_button(browser, "Serve")
    wait_until(lambda: ("serve", {"checkpoint": str((model / "policy.pt").resolve())}) in requests, WAIT,
               "the serve query")
    wait_until(lambda: f"from {(model / 'policy.pt').resolve()}" in page_text(browser), WAIT,
               lambda: f"the served checkpoint shown; page: {page_text(browser)[:800]}")
    neural_simulation(browser, session, requests, tmp_path)
    click_button(browser, "arm")
    wait_until(lambda: ("arm", {"armed": True}) in requests, WAIT, "the arm query")
    wait_until(lambda: "robot: ARMED" in page_text(browser), WAIT,
               lambda: f"the armed state shown; page: {page_text(browser)[:600]}")
    click_button(browser, "Close review")  # the scene shows the live cell again, where trajopt's trajectory is drawn
    wait_until(lambda: query_json(session, "xm/panel/main/@health")[0]["reviewing"] is None, WAIT, "the review closed")
    trajectory_drawn(browser, session, tmp_path)
    execution(browser, session, model, requests)
    click_button(browser, "STOP")
    wait_until(lambda: ("hold", {"disarm": True}) in requests, WAIT, "the stop query")
    wait_until(lambda: "robot: disarmed" in page_text(browser), WAIT,
               lambda: f"the disarmed state shown; page: {page_text(browser)[:600]}")


def neural_simulation(browser: Chromium, session, requests: list, tmp_path: Path) -> None:
    """The served network rolled out from the reviewed demonstration at the scrubber: the reply is
    drawn as a ghost over the scene (the 3D view changes) and the page says what was simulated."""
    before = viewport(browser.screenshot(tmp_path / "n0.png", PATIENCE_S))
    choose(browser, "start from", "the reviewed demonstration (scrubber)")
    click_button(browser, "Simulate")
    wait_until(lambda: any(v == "simulate" for v, _ in requests), WAIT, "the simulate query")
    _, req = next((v, r) for v, r in requests if v == "simulate")
    assert req["seconds"] == 3.0 and len(req["start"]["hands"]) == 2 * 21 * 3 and "checkpoint" not in req
    wait_until(lambda: "from the reviewed demonstration (scrubber):" in page_text(browser), WAIT,
               lambda: f"the rollout described; page: {page_text(browser)[-1500:]}")
    shown = query_json(session, "xm/panel/main/@health")[0]["neural_sim"]
    assert shown["runs"] == 1 and shown["shown"]["policy"] == "single_state" and shown["shown"]["steps"] > 2

    def ghost_drawn():
        shot = browser.screenshot(tmp_path / "n1.png", PATIENCE_S)
        return shot if np.abs(viewport(shot) - before).sum(axis=2).__gt__(60).mean() > 0.001 else None

    shot = wait_until(ghost_drawn, WAIT, "the ghost drawn in the 3D view", period=0.5)
    shutil.copy(shot, ROOT / ".cache" / "teaching_neural_sim.png")



def stand_in_world(session, requests: list) -> list:
    """The world's @cmd/reset, @cmd/mode and @cmd/outcome; its success test reports a seated module."""
    def answer(verb: str, query) -> None:
        req = json.loads((query.payload.to_bytes() if query.payload is not None else b"") or b"{}")
        requests.append((verb, req))
        reply = ({"ok": True, "task": "assembly", "mode": "robot", "sim_time": 9.0, "success": True, "seated": True,
                  "connector_gap_mm": 1.7} if verb == "outcome" else {"ok": True})
        query.reply(f"xm/world/sim/@cmd/{verb}", json.dumps(reply))

    return [session.declare_queryable(f"xm/world/sim/@cmd/{v}", lambda q, v=v: answer(v, q))
            for v in ("reset", "mode", "outcome")]


def trajectory_msg(shift: float) -> bytes:
    """A trajopt trajectory: 20 knots carrying the gripper 25 cm along x, the finger 15 cm along y."""
    robot = load_robot("workcell")
    names = list(robot.joint_names)
    knots = np.zeros((20, len(names)))
    knots[:, names.index("left_x")] = np.linspace(0.0, 0.25, 20) + shift
    knots[:, names.index("right_y")] = np.linspace(0.0, 0.15, 20)
    points = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=q, velocities=np.zeros(len(names)),
                        accelerations=np.zeros(0), effort=np.zeros(0),
                        time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=0, nanosec=int(k * 5e7)))
              for k, q in enumerate(knots)]
    return msgs.serialize(msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(time.time(), "world"),
                                    joint_names=names, points=points))


def trajectory_drawn(browser: Chromium, session, tmp_path: Path) -> None:
    """The optimizer's trajectory, published as trajopt does, is drawn in the 3-D scene (the rendered
    view changes) and hidden again once trajopt falls silent."""
    before = viewport(browser.screenshot(tmp_path / "t0.png", PATIENCE_S))
    pub = session.declare_publisher("xm/trajopt/main/trajectory")
    stop = threading.Event()

    def feed() -> None:  # as trajopt, 10 a second
        while not stop.wait(0.1):
            pub.put(trajectory_msg(0.0))

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        wait_until(lambda: (query_json(session, "xm/panel/main/@health")[0]["trajectory"] or {}).get("shown"), WAIT,
                   "the trajectory drawn")

        def drawn():
            shot = browser.screenshot(tmp_path / "t1.png", PATIENCE_S)
            return shot if np.abs(viewport(shot) - before).sum(axis=2).__gt__(60).mean() > 0.001 else None

        shot = wait_until(drawn, WAIT, "the trajectory in the rendered 3D view", period=0.5)
        shutil.copy(shot, ROOT / ".cache" / "teaching_trajectory.png")
        health = query_json(session, "xm/panel/main/@health")[0]
        assert health["trajectory"]["frames"] == ["left_tip_a", "left_tip_b", "right_tip"]
    finally:
        stop.set()
        feeder.join(5)
        pub.undeclare()
    wait_until(lambda: not query_json(session, "xm/panel/main/@health")[0]["trajectory"]["shown"], WAIT,
               "the trajectory hidden once trajopt is silent")


def execution(browser: Chromium, session, model: Path, requests: list) -> None:
    """Run execution: reset to the layout, robot mode, the world's test, teacher mode; the outcome
    logged beside the model, in the Execute folder, the model list and the session line. A long
    one: a second press meanwhile is told one runs, STOP ends it, logged as stopped."""
    type_into(browser, "layout seed", "4")
    type_into(browser, "run seconds", "2")
    wait_until(lambda: value_of(browser, "layout seed") == "4" and value_of(browser, "run seconds") == "2", WAIT,
               "the typed layout and duration")
    n = len(requests)
    click_button(browser, "Run execution")
    wait_until(lambda: "layout 4: success after" in page_text(browser), WAIT,
               lambda: f"the outcome shown; page: {page_text(browser)[-1500:]}")
    assert "connector gap 1.7 mm" in page_text(browser)
    assert [v for v, _ in requests[n:] if v in ("reset", "mode", "outcome")] == ["reset", "mode", "outcome", "mode"]
    assert ("reset", {"seed": 4}) in requests[n:] and ("mode", {"mode": "robot"}) in requests[n:]
    [logged] = [json.loads(line) for line in (model / "executions.jsonl").read_text().splitlines()]
    assert logged["success"] and logged["seed"] == 4 and logged["distances"] == {"connector_gap_mm": 1.7}
    assert logged["session"].startswith("pick_place-ada-") and logged["teacher"] == "ada"
    wait_until(lambda: "1 / 1 succeeded" in page_text(browser), WAIT, "the execution in the model list")
    assert "1 execution (1 succeeded)" in page_text(browser)  # the session line

    type_into(browser, "run seconds", "120")
    wait_until(lambda: value_of(browser, "run seconds") == "120", WAIT, "the long duration")
    m = len(requests)
    click_button(browser, "Run execution")
    wait_until(lambda: ("mode", {"mode": "robot"}) in requests[m:], WAIT, "the world in robot mode")
    click_button(browser, "Run execution")  # a second press while it runs is told so
    wait_until(lambda: "Execution refused" in page_text(browser), WAIT, "the second Run refused")
    click_button(browser, "STOP")
    wait_until(lambda: "layout 4: stopped after" in page_text(browser), WAIT,
               lambda: f"the stopped execution shown; page: {page_text(browser)[-1500:]}")
    lines = [json.loads(line) for line in (model / "executions.jsonl").read_text().splitlines()]
    assert len(lines) == 2 and lines[1]["stopped"] and not lines[1]["success"] and lines[1]["seconds"] < 120
    wait_until(lambda: "1 / 2 succeeded" in page_text(browser), WAIT, "both executions in the model list")
    health = query_json(session, "xm/panel/main/@health")[0]
    assert health["executions"]["runs"] == 2 and health["executions"]["last"]["stopped"]
