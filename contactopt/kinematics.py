"""A URDF robot as a batched, differentiable torch kinematic chain.

yourdfpy parses the file; this module keeps what the simulator needs: the joints in tree order
(origin, axis, revolute or prismatic), the coupling of mimic joints to the actuated degrees of
freedom (joint positions = C dof-space positions, C a 0/1 matrix), and the collision spheres
(the fingertips), whose world centers `sphere_centers` returns for joint positions q.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yourdfpy as ud

F64 = torch.float64


@dataclass
class Chain:
    joint_names: list[str]       # every moving joint, in tree order
    dof_names: list[str]         # the actuated ones (not mimic)
    coupling: torch.Tensor       # (n_joints, n_dof): q = coupling @ dof
    prismatic: torch.Tensor      # (n_joints,) bool
    lower: torch.Tensor          # (n_joints,) limits
    upper: torch.Tensor
    sphere_names: list[str]      # collision spheres, e.g. "ffdistal_tip"
    sphere_radius: torch.Tensor  # (S,)
    # internal: the joints grouped by depth in the tree, each level's constants stacked
    # (parent positions in the level above, O_R, O_t, O_R K, O_R K^2, O_R a, joint index or
    # n_joints for a fixed joint, revolute mask, prismatic mask), and per sphere (level, position,
    # offset in that frame)
    _levels: list[tuple[torch.Tensor, ...]]
    _spheres: list[tuple[int, int, torch.Tensor]]

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_dof(self) -> int:
        return len(self.dof_names)

    def sphere_centers(self, q: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """(B, S, 3) world centers of the collision spheres for joint positions q (B, n_joints) and
        the 4x4 world pose `base` of the root link."""
        b = q.shape[0]
        base = base.to(q.dtype)
        q_ext = torch.cat([q, torch.zeros(b, 1, dtype=q.dtype)], 1)  # column n_joints: fixed joints
        r, t = base[:3, :3].expand(b, 1, 3, 3), base[:3, 3].expand(b, 1, 3)
        frames = [(r, t)]
        for parent, o_r, o_t, o_rk, o_rk2, o_ra, index, rev, slide in self._levels:
            r_p, t_p = r[:, parent], t[:, parent]
            qq = q_ext[:, index]
            # translation: t_p + R_p (O_t + q O_R a) for prismatic joints
            t = t_p + (r_p @ (o_t + (qq * slide)[..., None] * o_ra)[..., None])[..., 0]
            # rotation (Rodrigues): R_p O_R (I + sin(q) K + (1 - cos(q)) K^2) for revolute joints
            a = (qq * rev)[..., None, None]
            r = r_p @ (o_r + torch.sin(a) * o_rk + (1 - torch.cos(a)) * o_rk2)
            frames.append((r, t))
        return torch.stack([frames[lv][1][:, k] + frames[lv][0][:, k] @ off for lv, k, off in self._spheres], 1)


def joint_terms(origin: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The constant factors of one joint's transform: O_R, O_t, O_R K, O_R K^2, O_R a (K the
    cross-product matrix of the unit axis a), so a step needs only one matrix product per joint."""
    k = torch.tensor([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]], dtype=F64)
    o_r, o_t = origin[:3, :3], origin[:3, 3]
    return o_r, o_t, o_r @ k, o_r @ k @ k, o_r @ axis


def load_chain(path: str | Path) -> Chain:
    """The chain of a URDF file; a missing or unreadable file is a ValueError naming the models
    that exist next to it."""
    path = Path(path)
    if not path.is_file():
        known = sorted(p.name for p in path.parent.glob("*.urdf")) if path.parent.is_dir() else []
        raise ValueError(f"no robot model {str(path)!r}; models: {', '.join(known) or 'none'}")
    robot = ud.URDF.load(str(path), build_scene_graph=False, load_meshes=False).robot
    children = {j.parent: [] for j in robot.joints}
    for j in robot.joints:
        children[j.parent].append(j)
    child_links = {j.child for j in robot.joints}
    root = next(link.name for link in robot.links if link.name not in child_links)
    moving = [j for j in robot.joints if j.type in ("revolute", "continuous", "prismatic")]
    # tree order (depth first from the root)
    order, stack = [], [root]
    while stack:
        link = stack.pop()
        for j in reversed(children.get(link, [])):
            order.append(j)
            stack.append(j.child)
    names = [j.name for j in order if j in moving]
    dofs = [j.name for j in order if j in moving and j.mimic is None]
    coupling = torch.zeros(len(names), len(dofs), dtype=F64)
    for i, j in enumerate(j for j in order if j in moving):
        coupling[i, dofs.index(j.mimic.joint if j.mimic else j.name)] = j.mimic.multiplier if j.mimic else 1.0
    depth, pos_in_level, levels = {root: 0}, {root: 0}, []
    for j in order:  # parents come before children
        lv = depth[j.parent] + 1
        depth[j.child] = lv
        if len(levels) < lv:
            levels.append([])
        pos_in_level[j.child] = len(levels[lv - 1])
        levels[lv - 1].append(j)
    packed = []
    for joints in levels:
        terms = [joint_terms(torch.tensor(j.origin, dtype=F64), unit_axis(j)) for j in joints]
        stacked = [torch.stack(c) for c in zip(*terms, strict=True)]
        index = torch.tensor([names.index(j.name) if j.name in names else len(names) for j in joints])
        rev = torch.tensor([float(j.type in ("revolute", "continuous")) for j in joints], dtype=F64)
        slide = torch.tensor([float(j.type == "prismatic") for j in joints], dtype=F64)
        packed.append((torch.tensor([pos_in_level[j.parent] for j in joints]), *stacked, index, rev, slide))
    spheres, sphere_names, radii = [], [], []
    for link in robot.links:
        for c in link.collisions:
            if c.geometry.sphere is not None:
                off = torch.tensor(c.origin if c.origin is not None else np.eye(4), dtype=F64)[:3, 3]
                spheres.append((depth[link.name], pos_in_level[link.name], off))
                sphere_names.append(c.name or link.name)
                radii.append(c.geometry.sphere.radius)
    by_name = {j.name: j for j in moving}
    lim = [(by_name[n].limit.lower, by_name[n].limit.upper) for n in names]
    return Chain(names, dofs, coupling, torch.tensor([by_name[n].type == "prismatic" for n in names]),
                 torch.tensor([lo for lo, _ in lim], dtype=F64), torch.tensor([hi for _, hi in lim], dtype=F64),
                 sphere_names, torch.tensor(radii, dtype=F64), packed, spheres)


def unit_axis(joint: ud.Joint) -> torch.Tensor:
    axis = torch.tensor(np.asarray(joint.axis if joint.axis is not None else (1, 0, 0), float), dtype=F64)
    return axis / axis.norm()
