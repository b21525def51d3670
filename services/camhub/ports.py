"""camhub: one trigger for every camera; the camera's name is the key's instance chunk."""

from shared.ports import CAMERAS, Input, Output, Ports, latest

PORTS = Ports(
    service="camhub",
    doc="synchronized camera frames",
    inputs=(
        Input("scene", "recon/main/scene", "xm_msgs/msg/Scene", latest(1),
              "tracked hands: each camera's region of interest follows them"),
    ),
    outputs=(
        Output("image", "sensor_msgs/msg/CompressedImage", 5.0, "JPEG frame, triggered together",
               key="xm/camhub/{each}/image", each=CAMERAS),
        Output("info", "sensor_msgs/msg/CameraInfo", 5.0, "intrinsics of the frame",
               key="xm/camhub/{each}/info", each=CAMERAS),
    ),
)
