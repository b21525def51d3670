"""Physical plausibility: the contact forces a policy predicts, replayed in MuJoCo.

The object (same shape, mass and start) lies on a table in MuJoCo; at every policy step the
forces the policy predicts for the finger-object pairs are applied to it at their response points
(held over the step's MuJoCo substeps), while MuJoCo computes everything else with its own
contact model: the table's support and friction (the policy's predicted table forces are not
replayed), or the revolute mount of task 8. The object's motion in MuJoCo is compared with the
differentiable simulator's: position and rotation at termination, and the task's metric.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import torch

from contactopt.sim3d import MASS, Rollout3D
from contactopt.tasks import Task
from contactopt.tasks3d import Task3D, task_metric

SUBSTEPS = 10
# MuJoCo prints a warning for every unstable step (a diverged policy's forces); they are counted
# in the result instead
mujoco.set_mju_user_warning(lambda _msg: None)
PLANAR_HEIGHT = 0.03  # the planar tasks' objects: 6 cm tall, forces applied at mid-height


def scene_xml(shape: str, half: tuple[float, float, float], table_mu: float, fixed: bool, dt: float) -> str:
    """MJCF of the object on a table (or on a vertical hinge above it)."""
    if shape == "box":
        geom = f'type="box" size="{half[0]} {half[1]} {half[2]}"'
    else:
        geom = f'type="cylinder" size="{half[0]} {half[2]}"'
    joint = '<joint name="mount" type="hinge" axis="0 0 1"/>' if fixed else '<freejoint name="free"/>'
    if fixed:  # mounted: the object does not touch the table
        geom += ' contype="0" conaffinity="0"'
    return f"""<mujoco>
  <option timestep="{dt / SUBSTEPS}" gravity="0 0 -9.81" cone="elliptic"/>
  <worldbody>
    <geom name="table" type="plane" size="1 1 0.1" friction="{table_mu} 0.005 0.0001"/>
    <body name="object" pos="0 0 {half[2]}">
      {joint}
      <geom name="object" {geom} mass="{MASS}" friction="{table_mu} 0.005 0.0001"/>
    </body>
  </worldbody>
</mujoco>"""


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two rotation matrices [rad]."""
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.acos(max(-1.0, min(1.0, c)))


def replay(xml: str, start: np.ndarray, forces: np.ndarray, points: np.ndarray, dt: float,
           fixed: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Replay one episode: start (3,) object center, forces and points (T, K, 3) in world frame.
    Returns positions (T+1, 3), rotations (T+1, 3, 3), angular velocities (T, 3) and how often
    MuJoCo found the simulation unstable (huge forces of a diverged policy; it resets then)."""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    body = model.body("object").id
    if fixed:
        model.body_pos[body] = start
    else:
        data.qpos[:3] = start
    mujoco.mj_forward(model, data)
    poss, rots, omegas = [data.xpos[body].copy()], [data.xmat[body].reshape(3, 3).copy()], []
    for f, p in zip(forces, points, strict=True):
        com = data.xipos[body]
        data.xfrc_applied[body, :3] = f.sum(0)
        data.xfrc_applied[body, 3:] = np.cross(p - com, f).sum(0)
        turned = np.zeros(3)
        for _ in range(SUBSTEPS):
            mujoco.mj_step(model, data)
            turned += data.cvel[body, :3] * model.opt.timestep  # world-frame angular velocity
        omegas.append(turned / dt)
        poss.append(data.xpos[body].copy())
        rots.append(data.xmat[body].reshape(3, 3).copy())
    unstable = int(data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number)
    return np.array(poss), np.array(rots), np.array(omegas), unstable


def compare(sim_pos: np.ndarray, sim_rot: np.ndarray, mj_pos: np.ndarray,
            mj_rot: np.ndarray) -> dict[str, float]:
    """Mean final position error [mm] and rotation error [deg] over episodes (B, T+1, ...)."""
    pos_err = np.linalg.norm(sim_pos[:, -1] - mj_pos[:, -1], axis=-1)
    rot_err = [rotation_angle(a, b) for a, b in zip(sim_rot[:, -1], mj_rot[:, -1], strict=True)]
    return {"replay_position_error_mm": float(1000 * pos_err.mean()),
            "replay_rotation_error_deg": float(math.degrees(np.mean(rot_err)))}


def replay3d(task: Task3D, ro: Rollout3D, n_tips: int) -> dict[str, float]:
    """Replay the fingertip forces of a 3-D rollout (batch B) in MuJoCo; errors and the metric."""
    s = ro.steps
    b, t = ro.pos.shape[0], ro.omega.shape[1]
    forces = s.force[:, :n_tips].reshape(b, t, n_tips, 3).detach().numpy()
    points = (0.5 * (s.p_a + s.p_b))[:, :n_tips].reshape(b, t, n_tips, 3).detach().numpy()
    xml = scene_xml(task.shape, task.half, 0.8, task.fixed, task.dt)
    runs = [replay(xml, ro.pos[i, 0].numpy(), forces[i], points[i], task.dt, task.fixed) for i in range(b)]
    mj_pos, mj_rot, mj_omega, unstable = (np.stack(x) for x in zip(*runs, strict=True))
    out = compare(ro.pos.numpy(), ro.rot.numpy(), mj_pos, mj_rot)
    out["replay_unstable"] = int(unstable.sum())
    out["replay_metric"] = task_metric(task, torch.from_numpy(mj_pos), torch.from_numpy(mj_omega))["metric"]
    return out


def replay_planar(task: Task, pos: torch.Tensor, theta: torch.Tensor, force: torch.Tensor,
                  point: torch.Tensor, table_mu: float) -> dict[str, float]:
    """Replay a planar rollout's predicted forces (B, T, 2, 2) at their response points on a
    6 cm tall object in MuJoCo; errors and the mean turn velocity about Z there."""
    b, t = force.shape[:2]
    half = (task.size, task.size, PLANAR_HEIGHT)
    xml = scene_xml(task.shape, half, table_mu, False, task.dt)
    z = np.zeros((b, t, force.shape[2], 1))
    f3 = np.concatenate([force.detach().numpy(), z], -1)
    p3 = np.concatenate([point.detach().numpy(), z + PLANAR_HEIGHT], -1)
    sim_pos = np.concatenate([pos.numpy(), np.full((b, t + 1, 1), PLANAR_HEIGHT)], -1)
    c, s = np.cos(theta.numpy()), np.sin(theta.numpy())
    zero, one = np.zeros_like(c), np.ones_like(c)
    sim_rot = np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1),
                        np.stack([zero, zero, one], -1)], -2)
    runs = [replay(xml, sim_pos[i, 0], f3[i], p3[i], task.dt, False) for i in range(b)]
    mj_pos, mj_rot, mj_omega, unstable = (np.stack(x) for x in zip(*runs, strict=True))
    out = compare(sim_pos, sim_rot, mj_pos, mj_rot)
    out["replay_unstable"] = int(unstable.sum())
    out["replay_metric"] = float(mj_omega[..., 2].mean())
    return out
