"""glove: one instance per hand; the instance name is the hand."""

from shared.ports import Output, Ports

PORTS = Ports(
    service="glove",
    doc="tactile glove driver: calibrated pressure",
    outputs=(
        Output("tactile", "xm_msgs/msg/Tactile", 100.0, "calibrated 16x16 pressure"),
        Output("raw", "xm_msgs/msg/TactileRaw", 100.0, "raw impedance", enabled_by="publish_raw"),
        Output("imu", "xm_msgs/msg/Imu", 100.0, "inertial unit", enabled_by="publish_imu"),
    ),
)
