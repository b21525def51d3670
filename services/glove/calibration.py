"""Per-cell calibration: complex cell measurement -> pressure, and fitting it from paired data.

Model (thesis 4.5.6): r = (C - C0)/C0 = a*p / (1 + b*p), so p = r / (a - b*r). The linear model
r = a*p is fitted too for comparison. Quality figures as in thesis 4.8.4: Pearson correlation
between predicted and reference force, and relative non-linearity (largest deviation of the
response from its linear fit, relative to the full-scale output).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.glove import layout


@dataclass
class Calibration:
    c0: np.ndarray  # (16,16) baseline capacitance
    a: np.ndarray  # (16,16) 1/kPa
    b: np.ndarray  # (16,16) 1/kPa
    mask: np.ndarray | None = None  # (16,16) 1 where the glove has a cell; None: the shipped layout's

    def __post_init__(self) -> None:
        if self.mask is None:
            self.mask = layout.default().mask
        # Per-frame constants, computed once (pressure runs at 1 kHz per glove).
        self._c0 = np.where(self.mask == 1, self.c0, 1.0)  # unpopulated crossings: no division by ~0
        self._r_max = 0.95 * self.a / np.maximum(self.b, 1e-9)  # beyond saturation: clamp, not blow up

    def pressure(self, impedance: np.ndarray) -> np.ndarray:
        r = np.minimum(np.asarray(impedance).imag / self._c0 - 1.0, self._r_max)
        p = r / (self.a - self.b * r)
        return (np.clip(p, 0.0, None) * self.mask).astype(np.float32)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps({"model": "rational", "c0": self.c0.tolist(), "a": self.a.tolist(),
                                          "b": self.b.tolist()}))

    @classmethod
    def load(cls, path: str | Path, mask: np.ndarray | None = None) -> Calibration:
        """A calibration file for the glove whose cells are ``mask`` (None: the shipped layout's)."""
        try:
            d = json.loads(Path(path).read_text())
            arrays = [np.asarray(d[k], float).reshape(16, 16) for k in ("c0", "a", "b")]
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"{path}: not a glove calibration file ({exc}); make one with `xm glove calibrate`") \
                from exc
        return cls(*arrays, mask=mask)


def rational(p: np.ndarray, a: float, b: float) -> np.ndarray:
    return a * p / (1.0 + b * p)


def fit_rational(p: np.ndarray, r: np.ndarray) -> tuple[float, float]:
    """Least-squares fit of r = a p / (1 + b p) (p reference pressure, r relative response)."""
    a0 = float(np.polyfit(p, r, 1)[0]) if len(p) > 1 else 0.01
    # scipy.optimize costs the glove service ~0.3 s of start-up and is only needed to fit: imported here.
    from scipy.optimize import least_squares

    res = least_squares(lambda x: rational(p, x[0], x[1]) - r, [max(a0, 1e-6), 1e-3], bounds=([0, 0], [np.inf, 10]))
    return float(res.x[0]), float(res.x[1])


def fit_linear(p: np.ndarray, r: np.ndarray) -> tuple[float, float]:
    slope, offset = np.polyfit(p, r, 1)
    return float(slope), float(offset)


def report(reference: np.ndarray, predicted: np.ndarray, response: np.ndarray) -> dict:
    """Thesis 4.8.4: Pearson correlation of predicted vs reference force/pressure, and relative
    non-linearity of the raw response: largest deviation from its least-squares line over the
    full-scale output span."""
    corr = float(np.corrcoef(reference, predicted)[0, 1])
    slope, offset = fit_linear(reference, response)
    full_scale = float(np.ptp(response)) or 1.0
    nonlin = float(np.max(np.abs(response - (slope * reference + offset))) / full_scale)
    return {"correlation": corr, "relative_nonlinearity": nonlin, "samples": int(len(reference))}


def plot_fit(pressure: np.ndarray, response: np.ndarray, a: float, b: float, png_path: str | Path,
             title: str = "") -> None:
    """Scatter of measured response over reference pressure with the rational and linear fits (PNG)."""
    import matplotlib  # optional heavy dependency, loaded only to draw the plot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.asarray(pressure, float)
    r = np.asarray(response, float)
    grid = np.linspace(0.0, max(float(p.max()), 1e-9), 100)
    slope, offset = fit_linear(p, r)
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(p, r, ".", ms=2, alpha=0.4, label="measured")
    ax.plot(grid, rational(grid, a, b), "k", label=f"rational a={a:.4f} b={b:.4f}")
    ax.plot(grid, slope * grid + offset, "r--", label="linear")
    ax.set_xlabel("reference pressure (kPa)")
    ax.set_ylabel("relative capacitance change")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
