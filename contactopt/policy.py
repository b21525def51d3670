"""The policy network (thesis 2.5-2.6): one hidden layer of 256 units, from object and joint
positions to joint velocity commands and, per shape pair, two contact-point candidates and a force."""

from __future__ import annotations

import torch
from torch import nn

N_JOINTS = 4
N_PAIRS = 2            # fingertip 1 - object, fingertip 2 - object
POS_SCALE = 0.05       # [m] input positions and output contact points are in these units
QDOT_SCALE = 2.0       # [rad/s] per unit of output
FORCE_SCALE = 1.0      # [N] per unit of output


class Policy(nn.Module):
    """Defaults: the planar two-finger policy; the 3-D tasks pass their input and output sizes
    (n_out = commands + 9 per shape pair)."""

    def __init__(self, hidden: int = 256, contacts: bool = True, n_in: int = 4 + N_JOINTS,
                 n_out: int | None = None) -> None:
        super().__init__()
        self.contacts = contacts
        if n_out is None:
            n_out = N_JOINTS + (6 * N_PAIRS if contacts else 0)
        self.net = nn.Sequential(nn.Linear(n_in, hidden), nn.Tanh(), nn.Linear(hidden, n_out))
        self.net.double()
        with torch.no_grad():  # start near rest: small commands, small forces
            self.net[2].weight.mul_(0.1)
            self.net[2].bias.zero_()

    def forward(self, obj_pos: torch.Tensor, obj_theta: torch.Tensor, q: torch.Tensor) -> tuple:
        """See `apply`."""
        w1, b1, w2, b2 = (p for p in self.parameters())
        return apply((w1, b1, w2, b2), obj_pos, obj_theta, q, self.contacts)


def mlp(params: tuple[torch.Tensor, ...], x: torch.Tensor) -> torch.Tensor:
    """The one-hidden-layer network on explicit parameters (W1, b1, W2, b2)."""
    w1, b1, w2, b2 = params
    return torch.addmm(b2, torch.tanh(torch.addmm(b1, x, w1.T)), w2.T)


def apply(params: tuple[torch.Tensor, ...], obj_pos: torch.Tensor, obj_theta: torch.Tensor,
          q: torch.Tensor, contacts: bool = True) -> tuple:
    """The network on explicit parameters (W1, b1, W2, b2), as plain tensor operations so that
    the optimizers can differentiate it twice cheaply. Returns joint velocity commands (B, 4) and,
    for the contact-based policy, per shape pair the raw outputs of the contact point on the
    finger side P_A (relative to the fingertip), on the object side P_B (relative to the object)
    and the force on the object F_C, each (B, 2, 2); the simulator scales them by POS_SCALE and
    FORCE_SCALE."""
    x = torch.cat([obj_pos / POS_SCALE, torch.cos(obj_theta)[:, None], torch.sin(obj_theta)[:, None], q], -1)
    y = mlp(params, x)
    qdot = QDOT_SCALE * y[:, :N_JOINTS]
    if not contacts:
        return qdot, None, None, None
    c = y[:, N_JOINTS:].reshape(-1, N_PAIRS, 6)
    return qdot, c[..., 0:2], c[..., 2:4], c[..., 4:6]
