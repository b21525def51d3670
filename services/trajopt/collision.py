"""Separating planes between the two arms of the workcell (thesis 7.21), initialised with coal.

Each pair is a convex shape of the left arm and one of the right arm (carriages, columns,
hands). At the start of a solve, coal's GJK/EPA gives the closest points and the separating
normal n for the current pose. Within the solve the plane normal is held fixed and the
constraint  n . (p_right(q) - p_left(q)) - (n . (p_right0 - p_left0) - d0) >= clearance  keeps
the shapes apart along it, where p are the link origins (the shapes translate with them: the
gantry's carriages and columns do not rotate).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import coal
import numpy as np

from shared.kinematics import RobotModel, Shape

PAIRS = [("left_carriage", "right_carriage"), ("left_column", "right_column"), ("left_hand", "right_hand"),
         ("left_carriage", "right_column"), ("left_column", "right_carriage")]


def _coal_shape(shape: Shape):
    if shape.kind == "box":
        return coal.Box(*shape.size)
    if shape.kind == "cylinder":
        return coal.Cylinder(shape.size[0], shape.size[1])
    return coal.Sphere(shape.size[0])


@dataclass
class ArmSeparation:
    model: RobotModel
    pairs: list[tuple[Shape, Shape]]
    clearance: float

    @classmethod
    def for_model(cls, model: RobotModel, clearance: float) -> ArmSeparation:
        by_link = {s.link: s for s in model.shapes}
        pairs = [(by_link[a], by_link[b]) for a, b in PAIRS if a in by_link and b in by_link]
        return cls(model, pairs, clearance)

    @property
    def n_rows(self) -> int:
        return len(self.pairs)

    @property
    def n_params(self) -> int:
        return 4 * max(1, len(self.pairs))  # normal (3) and offset (1) per pair

    def params(self, q: np.ndarray) -> np.ndarray:
        """GJK/EPA at pose q: per pair the unit normal (left -> right) and the offset so the
        constraint reads n.(o_R - o_L) - offset >= 0."""
        poses = self.model.fk(q)
        out = []
        for a, b in self.pairs:
            Ta, Tb = poses[a.link] @ a.origin, poses[b.link] @ b.origin
            req, res = coal.DistanceRequest(), coal.DistanceResult()
            req.enable_signed_distance = True
            d = coal.distance(_coal_shape(a), _transform(Ta), _coal_shape(b), _transform(Tb), req, res)
            normal = np.asarray(res.normal, float)
            if not np.isfinite(normal).all() or np.linalg.norm(normal) < 1e-9:
                normal = (Tb[:3, 3] - Ta[:3, 3]) / max(np.linalg.norm(Tb[:3, 3] - Ta[:3, 3]), 1e-9)
            normal = normal / np.linalg.norm(normal)
            oa, ob = poses[a.link][:3, 3], poses[b.link][:3, 3]
            offset = normal @ (ob - oa) - d + self.clearance
            out += [*normal, offset]
        return np.array(out if out else [0.0, 0.0, 1.0, -1.0])

    def constraint(self, q, sep):
        """n.(o_R(q) - o_L(q)) - offset per pair; works on SX and MX arguments."""
        if not self.pairs:
            return ca.SX.zeros(0)
        if not hasattr(self, "_fn"):
            q_s = ca.SX.sym("q", len(self.model.joint_names))
            sep_s = ca.SX.sym("sep", self.n_params)
            fk = self.model.fk_casadi(q_s)
            rows = [ca.dot(sep_s[4 * i:4 * i + 3], fk[b.link][1] - fk[a.link][1]) - sep_s[4 * i + 3]
                    for i, (a, b) in enumerate(self.pairs)]
            self._fn = ca.Function("separation", [q_s, sep_s], [ca.vertcat(*rows)])
        return self._fn(q, sep)


def _transform(T: np.ndarray):
    return coal.Transform3s(T[:3, :3], T[:3, 3])
