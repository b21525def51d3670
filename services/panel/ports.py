"""panel: the web dashboard; it keeps the newest message of each input and draws at its own rate."""

from shared.ports import CAMERAS, GLOVES, Input, Ports, latest

PORTS = Ports(
    service="panel",
    doc="viser dashboard",
    inputs=(
        Input("state", "robot/{robot}/state", "sensor_msgs/msg/JointState", latest(1), "robot pose"),
        Input("scene", "recon/main/scene", "xm_msgs/msg/Scene", latest(1), "keypoints"),
        Input("tactile_mesh", "recon/main/tactile_mesh", "xm_msgs/msg/TactileMesh", latest(1),
              "pressure on the gloved hands' surfaces"),
        Input("plan", "policy/main/plan", "xm_msgs/msg/Plan", latest(1), "planned keypoints"),
        Input("trajectory", "trajopt/main/trajectory", "trajectory_msgs/msg/JointTrajectory", latest(1),
              "the optimizer's joint trajectory, drawn as the paths of the robot's points"),
        Input("session", "world/sim/session", "xm_msgs/msg/Session", latest(1), "label"),
        Input("tactile", "glove/*/tactile", "xm_msgs/msg/Tactile", latest(len(GLOVES)), "heatmaps"),
        Input("info", "camhub/main/info", "sensor_msgs/msg/CameraInfo", latest(len(CAMERAS)), "frusta"),
        Input("image", "camhub/main/image", "sensor_msgs/msg/CompressedImage", latest(len(CAMERAS)),
              "thumbnail"),
    ),
)
