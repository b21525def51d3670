"""robot: the board driver. Its instance is named after the robot model, so its state key is
xm/robot/<model>/state, where trajopt and panel look for it."""

from shared.ports import Input, Output, Ports, latest

PORTS = Ports(
    service="robot",
    doc="robot board driver",
    inputs=(
        Input("trajectory", "trajopt/main/trajectory", "trajectory_msgs/msg/JointTrajectory", latest(1),
              "what to follow"),
    ),
    outputs=(
        Output("state", "sensor_msgs/msg/JointState", 100.0,
               "measured joint positions, velocities, motor currents as effort"),
    ),
)
