"""Contact-based policy optimization in differentiable simulators (thesis chapter 2).

`sim` steps a planar (top-view) world of two velocity-controlled fingers and a free object
(tasks 1-2) with simulated contacts (hard Hooke contact or the smooth softplus contact of
Eq. 2.1) or contacts the policy predicts (Eq. 2.2-2.4); `sim3d` a 3-D world of a URDF hand or
arm and hand (`kinematics`, `handmodel`) and a cube or cylinder (tasks 3-8) with predicted
contacts; `losses` and `losses3d` hold the five consistency losses (2.9-2.13); `optim` the
matrix-free Gauss-Newton optimizer with CG inner loop; `replay` replays predicted forces in
MuJoCo. See docs/contactopt.md.
"""
