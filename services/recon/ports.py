"""recon: keypoints of hands and objects from the cameras, the simulator's truth and touch."""

from shared.ports import CAMERAS, GLOVES, Input, Output, Ports, latest

PORTS = Ports(
    service="recon",
    doc="scene reconstruction",
    inputs=(
        Input("info", "camhub/main/info", "sensor_msgs/msg/CameraInfo", latest(len(CAMERAS)),
              "camera models"),
        Input("frame", "camhub/main/image", "sensor_msgs/msg/CompressedImage", latest(1),
              "the first camera's image marks a triggered frame set", only=CAMERAS[0]),
        Input("image", "camhub/main/image", "sensor_msgs/msg/CompressedImage", latest(2 * len(CAMERAS)),
              "every camera's JPEG readout window (the learned detector)"),
        Input("truth", "world/sim/truth", "xm_msgs/msg/GroundTruth", latest(64),
              "the simulated detector projects it (an option for experiments)"),
        Input("tactile", "glove/*/tactile", "xm_msgs/msg/Tactile", latest(2 * len(GLOVES)), "contact"),
    ),
    outputs=(
        Output("scene", "xm_msgs/msg/Scene", 5.0, "reconstructed keypoints"),
        Output("tactile_mesh", "xm_msgs/msg/TactileMesh", 5.0,
               "each gloved hand's surface mesh with its pressure per vertex (thesis 5.7)"),
    ),
)
