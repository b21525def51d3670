"""The thesis's validation function (3.3, suite 3): five coordinate frames, each turned about its
joint axis by an angle, composed and applied to a point; traced by autolin, and built again by
torch_reference.py and casadi_reference.py for the comparisons."""

from __future__ import annotations

import shared.autolin as al

AXES = ([0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0], [0, 0.6, 0.8], [0.48, 0.6, 0.64])
CHAIN_TYPES = ["quat"] * 5 + ["vec3"] * 5 + ["scalar"] * 5 + ["vec3"]


def chain(*a):
    """(q_1..q_5, t_1..t_5, angle_1..angle_5, point) -> (orientation, position) of the point."""
    qs, ts, th, p = a[0:5], a[5:10], a[10:15], a[15]
    q, t = qs[0] * al.angle_axis(th[0], AXES[0]), ts[0]
    for k in range(1, 5):
        t = t + q * ts[k]
        q = q * (qs[k] * al.angle_axis(th[k], AXES[k]))
    return q, t + q * p
