"""What a trained policy is (``ModelConfig``) and how the node rolls it out (``InferenceConfig``).

Both travel in the checkpoint as JSON; training's own settings (learning/presets.py) are kept
there for the record only.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields


@dataclass(frozen=True)
class ModelConfig:
    """The network of thesis 7.2 and the quantities its inputs and outputs are made of."""

    tactile: bool = True  # tactile inputs and outputs (7.2.10)
    memory: bool = True  # recurrent denoising with reservoir activations (7.2.8)
    masks: bool = True  # masked inputs/losses, masks predicted (7.2.5)
    pair_outputs: bool = True  # pairwise translation outputs (7.8), trained as an auxiliary loss
    dynamics: bool = True  # object dynamics J_D output and its plausibility loss (7.13-7.14)
    body_dynamics: bool = True  # J_D shared by the points of one rigid object (trained where any of them is seen)
    reservoir: int = 32  # reservoir size
    reservoir_radius: float = 0.98
    reservoir_periods: tuple[float, float] = (0.0, 0.0)  # s; > 0: W_R turns with these periods (log-spaced)
    hidden: tuple[int, ...] = (2048, 512, 512, 512)
    # time window (Table 7.1 row 4, window.py): block lengths of past samples, oldest first, the last
    # block the current sample; each older block's mean position adds inputs. (): the current sample only
    window: tuple[int, ...] = ()


@dataclass(frozen=True)
class InferenceConfig:
    """The consistency solve of each step (7.5, 7.9-7.10, 7.15)."""

    follow_unobserved: bool = True  # unobserved points move rigidly with their body's seen points
    w_dyn: float = 3.0  # weight of J_D V_pinch against the net's object velocity (7.15); 1.0 let the board drift
    w_memory_prior: float = 0.01  # weight of 7.9 (H = H_P) against 7.10 (H = H_prev + dH_P dt); 1.0 measured worse
    max_speed: float = 1.5  # m/s, bound applied before and after the dynamics reconciliation


def to_json(cfg) -> str:
    return json.dumps(asdict(cfg))


def from_json(cls, text: str):
    """A config dataclass from its JSON; an unknown field is an error (the checkpoint is of another version)."""
    data = json.loads(text)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown fields {unknown} (a checkpoint of another version: retrain it)")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})  # JSON has no tuples
