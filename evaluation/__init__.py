"""Offline evaluation of the policy: the Table 7.1 protocol (`xm eval`, evaluate.py) against the
baselines (baselines/), the robot in the loop (`xm eval --execute`, execute.py) with contact anchors
(anchors.py), and the torch reference the served compiled step is tested against (reference.py)."""
