"""foxglove: the Foxglove bridge. It forwards the keys its ``keys`` parameter names (any registered
type, raw CDR bytes), so those are not fixed here; it draws the scene and the robot's frames."""

from shared.ports import Input, Ports, latest

PORTS = Ports(
    service="foxglove",
    doc="Foxglove WebSocket bridge (optional)",
    inputs=(
        Input("scene", "recon/main/scene", "xm_msgs/msg/Scene", latest(1), "hands and objects as scene entities"),
        Input("state", "robot/{robot}/state", "sensor_msgs/msg/JointState", latest(1),
              "robot link frames (forward kinematics)"),
    ),
)
