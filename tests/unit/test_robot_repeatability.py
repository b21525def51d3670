"""The simulated robot repeats like a servo: table 6.1's single-axis tests, gripper included."""

import numpy as np

from services.robot.board_sim import axis_params
from services.robot.repeatability import Rig


def test_gripper_fingers_use_their_own_gains():
    assert axis_params("left_finger_a") != axis_params("left_y")
    assert axis_params("left_finger_a").effort_max <= 40.0  # the MuJoCo actuator's range


def test_gripper_reaches_and_repeats_its_commanded_opening():
    rig = Rig(0)
    home = rig.home()
    rig.move(home, 1.0)
    j = rig.names.index("left_finger_a")
    opened = home.copy()
    opened[j] = 0.02
    reached = []
    for _ in range(3):
        rig.move(opened, 0.5)
        reached.append(rig.sim.joint_state()[0][j])
        rig.move(home, 0.5)
    assert np.allclose(reached, 0.02, atol=2e-4), reached
    assert np.ptp(reached) < 1e-4
