"""policy: a keypoint plan per reconstructed scene."""

from shared.ports import Input, Output, Ports, latest

PORTS = Ports(
    service="policy",
    doc="chapter-7 policy (or the naive baseline)",
    inputs=(
        Input("scene", "recon/main/scene", "xm_msgs/msg/Scene", latest(1), "what it plans from"),
        Input("session", "world/sim/session", "xm_msgs/msg/Session", latest(1), "episode starts"),
    ),
    outputs=(
        Output("plan", "xm_msgs/msg/Plan", 5.0, "keypoint plan over a horizon, one per reconstructed scene"),
    ),
)
