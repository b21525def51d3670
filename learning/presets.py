"""Training settings and the recipes of Table 7.1's rows (1)-(4).

A ``Recipe`` is one trainable policy: its name, the network (``ModelConfig``), how it is trained
(``TrainConfig``) and how it is rolled out (``InferenceConfig``). Field names are unique across the
three, so ``Recipe.replace`` and the CLIs' ``--set KEY=VALUE`` (``config_changes``) take any of them.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields, replace

from services.policy.config import InferenceConfig, ModelConfig


@dataclass(frozen=True)
class TrainConfig:
    """Denoising samples (7.2.2, 7.6-7.7), augmentation (7.2.4, 7.6.8), losses and the optimizer."""

    denoise: bool = True  # 7.2.2
    rotate: bool = True  # 7.2.4: random rotations about gravity
    mirror: bool = True  # 7.6.8
    left_probability: float = 0.6  # 7.6.8
    noise_base: float = 10.0  # b_n
    noise_exponent: tuple[float, float] = (-3.3, -1.2)  # R_U: 0.5 mm .. 6 cm
    noise_gain: float = 8.0  # f_n (1/s): fraction of a displacement corrected per second
    rigid_noise: float = 1.0  # per-body translation noise, relative to the per-point noise
    object_noise: float = 0.5  # object noise relative to hand noise
    lag_noise: float = 0.25  # probability that a sample's noise is the scene lagging behind: positions of up to
    lag_s: float = 0.3  # this many seconds earlier (as a robot trails its plan), corrected like other noise
    goal_relative: bool = False  # denoising: a hand's target moves with the noise of the object it heads for next
    reservoir_noise: float = 20.0  # reservoir input noise per metre of position noise (in H std units)
    w_dH_loss: float = 1.0  # loss weight of the reservoir rate output (7.10 drives the memory at inference)
    w_plausible: float = 1e-3  # weight of the 7.14 plausibility loss on J_D
    pair_eps: float = 0.0025  # m^2 (5 cm): the bias of the 7.8 normalization of the pair loss
    steps: int = 8000  # the validation rollout still improved at 4000 (docs/policy.md)
    batch: int = 256
    lr: float = 1e-3
    ema: float = 0.999  # > 0: decay of a moving average of the weights, which is scored and kept
    eval_every: int = 500
    eval_from: float = 0.5  # first selection rollout at this fraction of the steps (best came at 7500 of 8000)
    seed: int = 0  # initial weights, reservoir, sample order and noise


_PARTS = {"model": ModelConfig, "train": TrainConfig, "inference": InferenceConfig}


@dataclass(frozen=True)
class Recipe:
    name: str = "multimodal"
    model: ModelConfig = ModelConfig()
    train: TrainConfig = TrainConfig()
    inference: InferenceConfig = InferenceConfig()

    def replace(self, **changes) -> Recipe:
        """This recipe with fields of any of its three configs (or ``name``) changed."""
        parts = {part: {} for part in _PARTS}
        for key, value in changes.items():
            if key == "name":
                continue
            part = FIELD_PART.get(key)
            if part is None:
                raise ValueError(f"unknown recipe field {key!r}")
            parts[part][key] = value
        return Recipe(changes.get("name", self.name),
                      **{part: replace(getattr(self, part), **parts[part]) for part in _PARTS})

    def to_json(self) -> str:
        return json.dumps(asdict(self))


FIELD_PART = {f.name: part for part, cls in _PARTS.items() for f in fields(cls)}

PRESETS: dict[str, Recipe] = {
    "multimodal": Recipe("multimodal", ModelConfig(reservoir_periods=(0.25, 8.0))),
    "no_tactile": Recipe("no_tactile", ModelConfig(tactile=False, reservoir_periods=(0.25, 8.0))),
    "single_state": Recipe("single_state", ModelConfig(tactile=False, memory=False)),  # no reservoir to fix
    # row (4): row (3) fed 16 samples, older ones averaged over 8, 4, 2, 1 (thesis 7.6.8), trained alike
    "time_window": Recipe("time_window", ModelConfig(tactile=False, memory=False, window=(8, 4, 2, 1, 1))),
}


def preset(name: str, **changes) -> Recipe:
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name].replace(**changes)


def quick_budget(recipe: Recipe, quick: bool) -> Recipe:
    """``recipe`` with the tiny --quick training budget (a smoke test), or as it is."""
    return recipe.replace(steps=5, hidden=(32, 32), batch=32) if quick else recipe


def config_changes(items: list[str]) -> dict:
    """``KEY=VALUE`` strings (the CLIs' ``--set``) as recipe changes, each typed like its field;
    tuples are comma-separated. ValueError names the bad item."""
    defaults = {k: v for part in _PARTS.values() for k, v in asdict(part()).items()}
    changes: dict = {}
    for item in items:
        key, sep, value = (part.strip() for part in item.partition("="))
        if not sep or key not in defaults:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE with KEY a field of ModelConfig, TrainConfig "
                             f"or InferenceConfig ({', '.join(defaults)})")
        current = defaults[key]
        try:
            if isinstance(current, bool):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                changes[key] = value.lower() in ("true", "1")
            elif isinstance(current, (tuple, list)):  # an empty default (window) holds integers
                kind = type(current[0]) if current else int
                changes[key] = tuple(kind(v) for v in value.split(",")) if value else ()
            else:
                changes[key] = type(current)(value)
        except ValueError:
            raise ValueError(f"--set {key}={value!r}: not a {type(current).__name__} like the default "
                             f"{current!r}") from None
    return changes
