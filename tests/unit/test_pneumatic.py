from __future__ import annotations

import numpy as np

from services.robot.pneumatic import P_MAX, MusclePair, SingleStageController, TwoStageController

DT = 0.001


def run(controller, plant: MusclePair, q_des: float, seconds: float) -> list[tuple[float, np.ndarray, float]]:
    out = []
    for _ in range(int(seconds / DT)):
        contact = plant.step(controller.command(q_des, plant, DT), DT)
        out.append((plant.q, plant.p.copy(), contact))
    return out


def test_two_stage_tracks_a_step():
    plant = MusclePair()
    trace = run(TwoStageController(), plant, 0.5, 3.0)
    assert abs(trace[-1][0] - 0.5) < 0.02
    assert max(q for q, _, _ in trace) < 0.5 * 1.3  # no wild overshoot


def test_two_stage_holds_a_contact_force_without_pressure_build_up():
    plant = MusclePair(wall=0.2)
    trace = run(TwoStageController(), plant, 0.6, 6.0)
    p_late = np.array([p for _, p, _ in trace[-2000:]])
    contact = np.array([c for _, _, c in trace[-2000:]])
    assert np.ptp(p_late[:, 0] - p_late[:, 1]) < 0.05  # the differential has settled
    assert p_late.max() < P_MAX - 0.5  # far from saturation
    assert contact.mean() > 0.02  # it does press on the obstacle
    single = run(SingleStageController(), MusclePair(wall=0.2), 0.6, 6.0)
    assert single[-1][1][0] > P_MAX - 0.05  # the single-stage scheme fills the muscle to the limit


def test_the_controller_runs_joints_as_arrays_like_one_controller_each():
    """The board runs one TwoStageController over all its joints (gains and state as arrays)."""
    plants = [MusclePair(), MusclePair(inertia=5e-4), MusclePair(wall=0.1)]
    singles = [TwoStageController(), TwoStageController(stiffness=4.0), TwoStageController(kd=0.5)]
    board = TwoStageController(np.array([6.0, 4.0, 6.0]), kd=np.array([0.3, 0.3, 0.5]), integral=np.zeros(3),
                               p_integral=np.zeros((2, 3)))
    twins = [MusclePair(), MusclePair(inertia=5e-4), MusclePair(wall=0.1)]
    target = np.array([0.5, -0.3, 0.4])
    for _ in range(500):
        for k in range(3):
            plants[k].step(singles[k].command(target[k], plants[k], DT), DT)
        p_des = board.pressures(target, np.array([t.q for t in twins]), np.array([t.qd for t in twins]), DT)
        valves = board.valves(p_des, np.array([t.p for t in twins]).T, DT)
        for k in range(3):
            twins[k].step(valves[:, k], DT)
    np.testing.assert_allclose([t.q for t in twins], [p.q for p in plants], atol=1e-12)
    np.testing.assert_allclose([t.p for t in twins], [p.p for p in plants], atol=1e-12)
