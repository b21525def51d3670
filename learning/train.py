"""The training loop of the chapter-7 policy.

``train(config, train_demos, val_demos, out_dir)``: Adam with a cosine schedule, a tqdm bar, and
with held-out demonstrations, in the schedule's second part (from ``eval_from``) every
``eval_every`` steps a neural-simulation rollout from each of their start states scored with the
Table 7.1 distance; the best checkpoint is kept. Without held-out demonstrations the final
(averaged) weights are kept: rollouts from the training starts cannot tell checkpoints apart
(docs/policy.md, Evidence). The checkpoint (state_dict + JSON config) loads with
``torch.load(weights_only=True)``; a loss-curve PNG and train.json go beside it.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from learning.metrics import trajectory_scores
from services.policy.model import PolicyError
from shared.demo import Demo


@dataclass
class TrainResult:
    checkpoint: Path | None  # best weights (None when no out_dir)
    best_step: int
    best_score: float  # mean hand + object distance (m) of the selection rollouts
    seconds: float  # wall time of the whole training
    seconds_to_best: float  # wall time until the best checkpoint was reached
    losses: list[float] = field(default_factory=list)
    evals: list[dict] = field(default_factory=list)
    method: object = None  # the trained learning.ours.Ours (not serialized)


def selection_score(method, demos: list[Demo]) -> dict[str, float]:
    """Mean Table 7.1 distances of rollouts from the demos' start states."""
    scores = []
    for d in demos:
        hands, objects = method.rollout(d, d.steps)
        scores.append(trajectory_scores(hands, objects, d, keys=("hand", "object")))
    res = {k: float(np.mean([s[k] for s in scores])) for k in ("hand", "object")}
    res["score"] = res["hand"] + res["object"]
    return res


def make_optimizer(net: torch.nn.Module, lr: float) -> torch.optim.Optimizer:
    """Adam, fused: one kernel over all parameters (18 -> 3 ms per step for the 4 M parameters of
    the preset, about 2 of its 10 minutes)."""
    return torch.optim.Adam(net.parameters(), lr=lr, fused=True)


def optimizer_step(method, opt: torch.optim.Optimizer, loss: torch.Tensor) -> None:
    """Backward, clipped step, and the folded inference copy dropped: the fused step updates the
    weights without bumping their version counters, which is how the copy notices other updates."""
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(method.net.parameters(), 10.0)
    opt.step()
    method.weights_updated()


class _Training:
    """One training run's state (``method``: a learning.ours.Ours)."""

    def __init__(self, method, train_demos: list[Demo]) -> None:
        cfg = method.recipe.train
        self.method, self.step = method, 0
        self.data = method.setup(train_demos)
        self.rng = np.random.default_rng(cfg.seed)
        self.opt = make_optimizer(method.net, cfg.lr)
        warm = max(1, cfg.steps // 20)

        def schedule(s: int) -> float:  # linear warm-up, cosine decay to 2 %
            return min(1.0, (s + 1) / warm) * (0.02 + 0.98 * 0.5 * (1 + np.cos(np.pi * min(s, cfg.steps) / cfg.steps)))

        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, schedule)
        self.params = list(method.net.parameters())
        self.ema = [p.detach().clone() for p in self.params] if cfg.ema else None  # weights averaged over the steps

    def advance(self) -> float:
        """One optimizer step; returns the loss."""
        method, cfg = self.method, self.method.recipe.train
        self.step += 1
        method.net.train()
        loss, _ = method.loss(method.make_batch(self.data, self.rng, cfg.batch))
        optimizer_step(method, self.opt, loss)
        self.sched.step()
        if self.ema is not None:
            with torch.no_grad():  # the usual warm-up: early weights do not linger
                w = 1.0 - min(cfg.ema, (1 + self.step) / (10 + self.step))
                torch._foreach_lerp_(self.ema, self.params, w)  # one call for all tensors (1.6 ms, 1.8 as a loop)
        method.losses.append(loss.item())
        if not np.isfinite(method.losses[-1]):
            raise PolicyError(f"training loss became {method.losses[-1]} at step {self.step}")
        return method.losses[-1]

    def score(self, demos: list[Demo]) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
        """Selection rollouts of the averaged weights; returns the scores and those weights."""
        net = self.method.net
        net.eval()
        current = [p.detach().clone() for p in self.params] if self.ema is not None else []
        with torch.no_grad():  # the averaged weights are scored (and kept); training goes on from its own
            for p, e in zip(self.params, self.ema or [], strict=False):
                p.copy_(e)
        try:
            sc = selection_score(self.method, demos)
        except PolicyError:
            sc = {"hand": np.inf, "object": np.inf, "score": np.inf}
        state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        with torch.no_grad():
            for p, c in zip(self.params, current, strict=False):
                p.copy_(c)
        return sc, state


def fit_model(method, train_demos: list[Demo], val_demos: list[Demo] | None, progress: bool = True,
              out_dir: Path | None = None, on_progress: Callable[[dict], None] | None = None) -> TrainResult:
    """Trains ``method`` (a learning.ours.Ours) in place; leaves it holding the best weights and,
    with ``out_dir``, writes policy.pt, config.json, train.json, loss.png and the training
    demonstrations (demos/, what the node's naive fallback replays). ``on_progress`` gets
    ``{"step", "steps", "loss"}`` (mean since the last report) about 200 times per run, and
    ``{"step", "steps", "eval"}`` after each selection rollout."""
    t0 = time.perf_counter()
    keep_best = bool(val_demos)  # else the final weights are kept, and the training starts scored once, at the end
    scored = val_demos or train_demos
    best = {"score": np.inf, "step": 0, "state": None, "t": 0.0}
    evals: list[dict] = []
    run = _Training(method, train_demos)
    cfg = method.recipe.train
    report_every = max(1, cfg.steps // 200)
    if on_progress is not None:
        on_progress({"step": 0, "steps": cfg.steps})
    bar = tqdm(range(run.step + 1, cfg.steps + 1), desc=f"train {method.name}", disable=not progress, leave=False)
    for step in bar:
        run.advance()
        if step % 50 == 0:
            bar.set_postfix(loss=f"{np.mean(method.losses[-50:]):.4f}")
        if on_progress is not None and (step % report_every == 0 or step == cfg.steps):
            on_progress({"step": step, "steps": cfg.steps, "loss": float(np.mean(method.losses[-report_every:]))})
        # selection rollouts (~10 s each) only once the cosine schedule has decayed: the best comes late
        if step == cfg.steps or (keep_best and step % cfg.eval_every == 0 and step >= cfg.eval_from * cfg.steps):
            sc, state = run.score(scored)
            sc["step"], sc["seconds"] = step, time.perf_counter() - t0
            evals.append(sc)
            if on_progress is not None:
                on_progress({"step": step, "steps": cfg.steps, "eval": {k: float(sc[k]) for k in ("hand", "object",
                                                                                                 "score")}})
            if sc["score"] < best["score"] or not keep_best:
                best = {"score": sc["score"], "step": step, "t": sc["seconds"], "state": state}
            if progress:
                bar.write(f"step {step}: rollout hand {sc['hand'] * 1e3:.1f} mm, object {sc['object'] * 1e3:.1f} mm")
    net = method.net
    if best["state"] is not None:
        net.load_state_dict(best["state"])
    net.eval()
    method.weights_updated()
    seconds = time.perf_counter() - t0
    method.train_seconds = seconds
    result = TrainResult(None, best["step"], float(best["score"]), seconds, best["t"], list(method.losses), evals)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        result.checkpoint = out_dir / "policy.pt"
        method.save(str(result.checkpoint))
        (out_dir / "config.json").write_text(method.recipe.to_json())
        (out_dir / "train.json").write_text(json.dumps(
            {"preset": method.name, "train_demos": len(train_demos), "selection_demos": len(val_demos or []),
             "kept": "best on the held-out demonstrations" if keep_best else "final weights",
             "best_step": best["step"], "best_score_m": result.best_score, "seconds": seconds,
             "seconds_to_best": best["t"], "evals": evals}, indent=2, default=float))
        plot_losses(np.array(method.losses), evals, out_dir / "loss.png")
        save_demos(out_dir / "demos", train_demos)
    return result


def save_demos(folder: Path, demos: list[Demo]) -> None:
    """The training demonstrations (what the policy node's naive fallback replays), replacing the
    folder's in one rename: a reader sees the old set or the new one."""
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for i, demo in enumerate(demos):
        demo.save(tmp / f"demo_{i:03d}.npz")
    old = folder.with_name(folder.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if folder.exists():
        os.replace(folder, old)
    os.replace(tmp, folder)
    shutil.rmtree(old, ignore_errors=True)


def plot_losses(losses: np.ndarray, evals: list[dict], path: Path) -> None:
    import matplotlib  # optional heavy dependency, loaded only to draw the plot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.5))
    ax.semilogy(losses, lw=0.5, alpha=0.35, label="batch loss")
    k = max(1, len(losses) // 60)
    if len(losses) >= k:
        ax.semilogy(np.arange(k - 1, len(losses)), np.convolve(losses, np.ones(k) / k, mode="valid"), lw=1.5,
                    label="smoothed")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    if evals:
        ax2 = ax.twinx()
        ax2.plot([e["step"] for e in evals], [e["score"] * 1e3 for e in evals], "o-", color="tab:red",
                 label="rollout distance")
        ax2.set_ylabel("rollout hand+object (mm)", color="tab:red")
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
