"""recon: keypoints of hands and objects from the cameras and touch. The simulator's truth is read
only with ``detector = "simulated"`` (an option for experiments): its inputs exist only then."""

from shared.ports import CAMERAS, GLOVES, Input, Output, Ports, latest

SIMULATED = ("detector", "simulated")
# Frame sets recon may fall behind by before it drops images or their CameraInfos: a slow frame set
# (the network and the fits run in the handler) must not cost the next ones.
BACKLOG = 4

PORTS = Ports(
    service="recon",
    doc="scene reconstruction",
    inputs=(
        Input("info", "camhub/main/info", "sensor_msgs/msg/CameraInfo", latest(BACKLOG * len(CAMERAS)),
              "camera models and each frame set's readout windows"),
        Input("image", "camhub/main/image", "sensor_msgs/msg/CompressedImage", latest(BACKLOG * len(CAMERAS)),
              "every camera's JPEG readout window (the learned detector)"),
        Input("frame", "camhub/main/image", "sensor_msgs/msg/CompressedImage", latest(1),
              "the first camera's image marks a triggered frame set (simulated detector)", only=CAMERAS[0],
              when=SIMULATED),
        Input("truth", "world/sim/truth", "xm_msgs/msg/GroundTruth", latest(64),
              "the simulated detector projects it (an option for experiments)", when=SIMULATED),
        Input("tactile", "glove/*/tactile", "xm_msgs/msg/Tactile", latest(2 * len(GLOVES)), "contact"),
    ),
    outputs=(
        Output("scene", "xm_msgs/msg/Scene", 5.0, "reconstructed keypoints"),
        Output("tactile_mesh", "xm_msgs/msg/TactileMesh", 5.0,
               "each gloved hand's surface mesh with its pressure per vertex (thesis 5.7)"),
    ),
)
