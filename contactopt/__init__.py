"""Contact-based policy optimization in a small differentiable simulator (thesis chapter 2).

`sim` steps a planar (top-view) rigid-body world of two velocity-controlled fingers and a free
object with either simulated contacts (hard Hooke contact or the smooth softplus contact of
Eq. 2.1) or contacts the policy predicts (Eq. 2.2-2.4); `losses` holds the five consistency
losses (2.9-2.13); `optim` the matrix-free Gauss-Newton optimizer with CG inner loop.
See docs/contactopt.md.
"""
