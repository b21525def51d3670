"""Linear reservoir of thesis 7.2.8 (eqs 7.11-7.12), pure numpy.

H_{t+1} = W_R H_t + W_I m_t V_t, run forwards and backwards in time over masked keypoint
velocities, H_t = H_{t,+1} + H_{t,-1}. W_R is a random orthogonal matrix scaled to ``radius``
(the decay per step sets the memory span: 0.98 at 50 Hz is about one second), W_I is Gaussian.
A random orthogonal matrix turns nearly all of its state quickly (rotation periods of a few
steps) and keeps one slow direction, chosen by chance; ``periods`` instead fixes the
rotation periods, spread log-evenly, and leaves only the eigenbasis random (docs/policy.md,
Evidence).

Because the map is linear, a rotation of the velocities about gravity by angle a gives
H = cos(a) H_xy + sin(a) H_perp + H_z, so rotated activations are precomputed exactly
(``components``) instead of rerunning the reservoir per augmentation.
"""

from __future__ import annotations

import numpy as np


class Reservoir:
    def __init__(self, points: int, size: int = 32, radius: float = 0.98, seed: int = 0,
                 periods: tuple[float, float] | None = None) -> None:
        """periods: (shortest, longest) rotation period in steps, or None for a plain random orthogonal W_R."""
        rng = np.random.default_rng(seed)
        q, _ = np.linalg.qr(rng.normal(size=(size, size)))
        if periods is not None:  # the same eigenbasis q, rotated by fixed angles pairwise
            turns = np.zeros((size, size))
            for i, period in enumerate(np.geomspace(periods[0], periods[1], size // 2)):
                c, s = np.cos(2 * np.pi / period), np.sin(2 * np.pi / period)
                turns[2 * i:2 * i + 2, 2 * i:2 * i + 2] = [[c, -s], [s, c]]
            if size % 2:
                turns[-1, -1] = 1.0
            q = q @ turns @ q.T
        self.W_R = (radius * q).astype(np.float64)
        self.W_I = rng.normal(0.0, 1.0 / np.sqrt(3 * points), (size, 3 * points))
        self.size, self.points = size, points

    def run(self, v: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """v: (T, points, 3) velocities, mask: (T, points) observed. Returns H (T, size), eq. 7.12."""
        T = len(v)
        drive = (np.asarray(v, float) * np.asarray(mask, float)[..., None]).reshape(T, -1) @ self.W_I.T
        fwd = np.zeros((T, self.size))
        bwd = np.zeros((T, self.size))
        for t in range(1, T):
            fwd[t] = self.W_R @ fwd[t - 1] + drive[t - 1]
        for t in range(T - 2, -1, -1):
            bwd[t] = self.W_R @ bwd[t + 1] + drive[t + 1]
        return fwd + bwd

    def components(self, v: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(3, T, size): activations of the xy part, of the xy part turned by 90 degrees, of z."""
        v = np.asarray(v, float)
        xy, perp, z = np.zeros_like(v), np.zeros_like(v), np.zeros_like(v)
        xy[..., :2] = v[..., :2]
        perp[..., 0], perp[..., 1] = -v[..., 1], v[..., 0]
        z[..., 2] = v[..., 2]
        return np.stack([self.run(xy, mask), self.run(perp, mask), self.run(z, mask)])

    @staticmethod
    def rotated(components: np.ndarray, angle: np.ndarray) -> np.ndarray:
        """Activations of rotated velocities from ``components`` (3, ..., size); angle broadcasts."""
        a = np.asarray(angle)[..., None]
        return np.cos(a) * components[0] + np.sin(a) * components[1] + components[2]

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"W_R": self.W_R, "W_I": self.W_I}

    @classmethod
    def from_arrays(cls, W_R: np.ndarray, W_I: np.ndarray) -> Reservoir:
        self = cls.__new__(cls)
        self.W_R, self.W_I = np.asarray(W_R, np.float64), np.asarray(W_I, np.float64)
        self.size, self.points = self.W_R.shape[0], self.W_I.shape[1] // 3
        return self
