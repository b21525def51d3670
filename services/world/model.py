"""The MuJoCo model of the simulated workcell, built with MjSpec from the robot's URDF.

Table top at z=0, the robot from its description (shared/robots; the deployment picks it: the
gantry by default, or the 6-DoF arm with a four-finger hand) with the description's joint dynamics
and a motor per listed joint, limited to its URDF effort (the control-board simulator computes the
efforts; MuJoCo's URDF importer turns each ``<mimic>`` into a joint equality, so coupled joints have
no motor), task objects as free bodies, the
teacher's hand keypoints as mocap bodies (services/world/render.py draws the hands and the room), a
ChArUco calibration board as a mocap plate (hidden under the table until ``xm calibrate`` moves it),
and 7 cameras on the top of an 80 cm cube frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from services.world import bottle, wiping
from shared.charuco import BoardSpec
from shared.geometry import look_at
from shared.kinematics import load_robot
from shared.robots.registry import DEFAULT_ROBOT, describe

FRAME_SIZE = 0.8
CAMERA_HEIGHT = 0.8
CAMERA_FOVY_DEG = 60.0
PHYSICS_DT = 0.002
LATCH = "connector_latch"  # weld equality camera -> board
# Contacts of the task objects: MuJoCo's soft contacts scale with the bodies' mass, and with the
# default 20 ms time constant a gripper squeezing a 3 g module sinks millimetres into it; the
# shortest time constant the step allows keeps that to a fraction of a millimetre.
OBJECT_SOLREF = [2 * PHYSICS_DT, 1.0]
CALIB_BOARD = "calib_board"  # mocap body whose frame is the board frame of shared/charuco.py
CALIB_BOARD_PX = 96  # texture pixels per chessboard square: sharper than any camera sees it

# (x, y) of the 7 cameras on the top beams; the front beam is set back (thesis 5.4).
CAMERA_XY = [(-0.4, -0.4), (-0.4, 0.0), (-0.4, 0.4), (0.4, -0.4), (0.4, 0.4), (0.15, -0.4), (0.15, 0.4)]
LOOK_AT = np.array([0.03, 0.0, 0.02])

OBJECTS = {  # name -> list of (geom type, size (half extents), offset, rgba, mass)
    "assembly": {
        "board": [("box", (0.030, 0.015, 0.0008), (0.0, 0.0, 0.0008), (0.1, 0.5, 0.2, 1), 0.007),
                  ("box", (0.003, 0.003, 0.0007), (-0.012, 0.0, 0.0023), (0.8, 0.8, 0.8, 1), 0.0005)],
        "camera": [("box", (0.003, 0.003, 0.002), (0.0, 0.0, 0.002), (0.05, 0.05, 0.05, 1), 0.002),
                   ("box", (0.016, 0.0025, 0.0002), (0.018, 0.0, 0.0005), (0.8, 0.5, 0.1, 1), 0.0005),
                   ("box", (0.003, 0.002, 0.0007), (0.036, 0.0, 0.0022), (0.7, 0.7, 0.7, 1), 0.0005)],
    },
    "pick_place": {
        "box": [("box", (0.025, 0.025, 0.025), (0.0, 0.0, 0.025), (0.8, 0.3, 0.1, 1), 0.05)],
        "plate": [("box", (0.06, 0.06, 0.0025), (0.0, 0.0, 0.0025), (0.3, 0.3, 0.8, 1), 0.2)],
    },
    "wiping": wiping.GEOMS,
    "bottle": bottle.GEOMS,
}
GEOM_TYPES = {"box": mujoco.mjtGeom.mjGEOM_BOX, "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
              "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER}
OBJECTS["latch"] = OBJECTS["assembly"]
ASSEMBLY_TASKS = ("assembly", "latch")  # the tasks with the connector's snap-fit


@dataclass
class CameraSpec:
    name: str
    width: int
    height: int
    K: np.ndarray  # (3,3)
    world_T_cam: np.ndarray  # (4,4), OpenCV axes: x right, y down, z forward


def camera_specs(width: int = 320, height: int = 240) -> list[CameraSpec]:
    fy = (height / 2) / np.tan(np.radians(CAMERA_FOVY_DEG) / 2)
    K = np.array([[fy, 0, width / 2], [0, fy, height / 2], [0, 0, 1.0]])
    specs = []
    for i, (x, y) in enumerate(CAMERA_XY):
        specs.append(CameraSpec(f"cam{i}", width, height, K, look_at(np.array([x, y, CAMERA_HEIGHT]), LOOK_AT)))
    return specs


def build_model(task: str = "assembly", width: int = 320, height: int = 240,
                robot: str = DEFAULT_ROBOT) -> mujoco.MjModel:
    desc = describe(robot)  # UnknownRobotError (a ValueError) names the known robots
    spec = mujoco.MjSpec.from_file(str(desc.urdf))
    spec.option.timestep = PHYSICS_DT
    # The URDF importer's discardvisual would also strip the calibration board's texture; the model's
    # other visual-only geoms are hidden instead (_add_calibration_board), so images stay as they were.
    spec.compiler.discardvisual = False
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC  # with impratio: grasps that do not creep
    spec.option.impratio = 10.0
    spec.visual.quality.shadowsize = 0  # software GL: shadows cost more than they show
    spec.visual.global_.offwidth = max(width, 640)
    spec.visual.global_.offheight = max(height, 480)
    # Robot links do not collide with each other in physics (link boxes overlap at the joints; the
    # trajectory optimizer keeps the arms apart); they do collide with the table and objects.
    for geom in spec.geoms:
        geom.contype, geom.conaffinity = 2, 1
    world = spec.worldbody
    world.add_light(pos=[0, 0, 1.5], dir=[0, 0, -1], diffuse=[0.8, 0.8, 0.8], castshadow=False)
    world.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[FRAME_SIZE / 2, FRAME_SIZE / 2, 0.01],
                   rgba=[0.7, 0.67, 0.6, 1], contype=1, conaffinity=3)  # light laminate
    for x in (-0.4, 0.4):  # frame posts and top beams: visual only
        for y in (-0.4, 0.4):
            world.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.01, 0.01, 0.4], pos=[x, y, 0.4],
                           rgba=[0.3, 0.3, 0.3, 1], contype=0, conaffinity=0)
    _drives(spec, robot)
    if task not in OBJECTS:
        raise ValueError(f"unknown task {task!r} (known: {', '.join(OBJECTS)})")
    for name, geoms in OBJECTS[task].items():
        body = world.add_body(name=name, pos=[0, 0, 0])
        body.add_freejoint(name=f"{name}_free")
        for gtype, size, offset, rgba, mass in geoms:
            body.add_geom(type=GEOM_TYPES[gtype],
                          size=list(size), pos=list(offset), rgba=list(rgba), mass=mass, friction=[1.0, 0.01, 0.001],
                          contype=1, conaffinity=3, solref=OBJECT_SOLREF)
    if task in ASSEMBLY_TASKS:  # the connector's snap-fit, engaged by WorldSim when pressed home (robot mode)
        spec.add_equality(name=LATCH, type=mujoco.mjtEq.mjEQ_WELD, objtype=mujoco.mjtObj.mjOBJ_BODY,
                          name1="camera", name2="board", active=0,
                          solref=[2 * PHYSICS_DT, 1.0])  # as stiff as the step allows
    # The teacher's hand keypoints: mocap bodies carrying the pose only (their visual-only spheres are
    # hidden, see _add_calibration_board); services/world/render.py draws the hands.
    for h, hand in enumerate(("left", "right")):
        rgba = [0.9, 0.6, 0.5, 1] if h == 0 else [0.5, 0.6, 0.9, 1]
        for k in range(21):
            body = world.add_body(name=f"{hand}_kp{k}", mocap=True, pos=[0, 0, -1])
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.007 if k % 4 else 0.009, 0, 0], rgba=rgba,
                          contype=0, conaffinity=0)
    _add_calibration_board(spec, BoardSpec())
    for cam in camera_specs(width, height):
        R = cam.world_T_cam[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenCV -> MuJoCo camera axes
        world.add_camera(name=cam.name, pos=list(cam.world_T_cam[:3, 3]), fovy=CAMERA_FOVY_DEG,
                         xyaxes=list(R[:, 0]) + list(R[:, 1]))
    return spec.compile()


def _add_calibration_board(spec: mujoco.MjSpec, board: BoardSpec) -> None:
    """A thin textured box whose -z face, in the board's own frame (z into the board), is the print,
    with a grey backing plate behind it; it collides with nothing."""
    for geom in spec.geoms:  # what discardvisual dropped (visual-only geoms) stays out of the images
        if geom.contype == 0 and geom.conaffinity == 0:
            geom.rgba[3] = 0.0
    image = board.image(CALIB_BOARD_PX)[::-1]  # MuJoCo's texture rows run bottom-up
    tex = spec.add_texture(name=CALIB_BOARD, type=mujoco.mjtTexture.mjTEXTURE_2D, width=image.shape[1],
                           height=image.shape[0], nchannel=3)
    tex.data = np.repeat(image[:, :, None], 3, axis=2).tobytes()
    mat = spec.add_material(name=CALIB_BOARD, texuniform=False, texrepeat=[1, 1])
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = CALIB_BOARD
    w, h = board.size_m
    body = spec.worldbody.add_body(name=CALIB_BOARD, mocap=True, pos=[0, 0, -1])
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[w / 2, h / 2, 0.0005], pos=[w / 2, h / 2, 0.0005],
                  material=CALIB_BOARD, contype=0, conaffinity=0, mass=0.1)
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[w / 2, h / 2, 0.0015], pos=[w / 2, h / 2, 0.0027],
                  rgba=[0.5, 0.5, 0.5, 1], contype=0, conaffinity=0, mass=0.1)  # covers the mirrored print


def _drives(spec: mujoco.MjSpec, robot: str) -> None:
    """Joint damping and armature from the description, and a motor per listed joint limited to the
    URDF effort (mimic joints follow their masters by equality)."""
    desc, model = describe(robot), load_robot(robot)
    effort = {j.name: j.effort for j in model.moving}
    for joint in spec.joints:
        damping, armature = desc.sim_dynamics[joint.name]
        joint.damping = [damping, 0, 0]
        joint.armature = armature
    for name in desc.sim_motors:
        spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT,
                          ctrlrange=[-effort[name], effort[name]], ctrllimited=True, gear=[1, 0, 0, 0, 0, 0])
