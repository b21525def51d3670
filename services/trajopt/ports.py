"""trajopt: joint trajectories that follow the plan's keypoints."""

from shared.ports import Input, Output, Ports, latest

PORTS = Ports(
    service="trajopt",
    doc="trajectory optimizer",
    inputs=(
        Input("plan", "policy/main/plan", "xm_msgs/msg/Plan", latest(1), "keypoints to follow"),
        Input("state", "robot/{robot}/state", "sensor_msgs/msg/JointState", latest(1), "where the robot is"),
    ),
    outputs=(
        Output("trajectory", "trajectory_msgs/msg/JointTrajectory", 10.0, "joint trajectory for the robot"),
    ),
)
