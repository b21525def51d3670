"""world: the simulated workcell. It hosts the gloves' and the robot board's devices on ptys."""

from shared.ports import Output, Ports

PORTS = Ports(
    service="world",
    doc="MuJoCo workcell: clock, truth, session label; hosts the simulated devices",
    hosts_devices=True,
    outputs=(
        Output("clock", "rosgraph_msgs/msg/Clock", 100.0, "simulated time", key="xm/clock"),
        Output("truth", "xm_msgs/msg/GroundTruth", 50.0, "simulator truth, for evaluation only"),
        Output("session", "xm_msgs/msg/Session", 1.0, "task/demo/phase label", on_change=True),
    ),
)
