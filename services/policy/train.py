"""Training of the chapter-7 policy, and `xm train`.

``train(config, train_demos, val_demos, out_dir)``: Adam with a cosine schedule, a tqdm bar, and
with held-out demonstrations, in the schedule's second part (from ``eval_from``) every
``eval_every`` steps a neural-simulation rollout from each of their start states scored with the
Table 7.1 distance; the best checkpoint is kept. Without held-out demonstrations the final
(averaged) weights are kept: rollouts from the training starts cannot tell checkpoints apart
(docs/policy.md, Session 15). The checkpoint (state_dict + JSON config) loads with
``torch.load(weights_only=True)``; a loss-curve PNG and train.json go beside it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

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


def selection_score(method, demos: list[Demo]) -> dict[str, float]:
    """Mean Table 7.1 distances of rollouts from the demos' start states (training mode left off)."""
    from services.policy.metrics import trajectory_scores

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
    """One draw's training state. Stepping is deterministic, so a candidate draw that is kept
    after its first steps ends exactly where its training alone would have."""

    def __init__(self, method, train_demos: list[Demo]) -> None:
        cfg = method.cfg
        self.method, self.step = method, 0
        self.data = method.setup(train_demos)
        self.rng = np.random.default_rng(cfg.init_seed)
        self.opt = make_optimizer(method.net, cfg.lr)
        warm = max(1, cfg.steps // 20)

        def schedule(s: int) -> float:  # linear warm-up, cosine decay to 2 %
            return min(1.0, (s + 1) / warm) * (0.02 + 0.98 * 0.5 * (1 + np.cos(np.pi * min(s, cfg.steps) / cfg.steps)))

        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, schedule)
        self.params = list(method.net.parameters())
        self.ema = [p.detach().clone() for p in self.params] if cfg.ema else None  # weights averaged over the steps

    def advance(self) -> float:
        """One optimizer step; returns the loss."""
        from services.policy.ours import PolicyError

        method, cfg = self.method, self.method.cfg
        self.step += 1
        method.net.train()
        if cfg.recurrent:  # 7.2.7: trajectories with integrated positions and resets
            loss, _ = method.sequence_loss(self.data, self.rng)
        else:
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
        from services.policy.ours import PolicyError

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


def pick_candidate(method, train_demos: list[Demo], scored: list[Demo], progress: bool
                   ) -> tuple[_Training, list[dict], dict[str, torch.Tensor]]:
    """Trains ``cfg.candidates`` draws for ``cfg.candidate_steps`` steps each and returns the run of
    the one whose selection rollouts score best (``method`` now holds it), every draw's scores,
    and the kept draw's scored (averaged) weights (docs/policy.md, Session 19)."""
    from tqdm import tqdm

    cfg = method.cfg
    scores: list[dict] = []
    kept: tuple[_Training, dict[str, torch.Tensor], float] | None = None  # only the best so far stays in memory
    for k in range(cfg.candidates):
        draw = cfg.replace(candidate=k)
        if k == 0:
            m, method.cfg = method, draw
        else:
            m = method.sibling(draw)
        run = _Training(m, train_demos)
        for _ in tqdm(range(cfg.candidate_steps), desc=f"train {cfg.name} draw {k + 1}/{cfg.candidates}",
                      disable=not progress, leave=False):
            run.advance()
        sc, state = run.score(scored)
        scores.append({"candidate": k, "hand": sc["hand"], "object": sc["object"], "score": sc["score"]})
        if kept is None or sc["score"] < kept[2]:
            kept = (run, state, sc["score"])
        if progress:
            tqdm.write(f"draw {k + 1}/{cfg.candidates} at step {cfg.candidate_steps}: "
                       f"rollout hand {sc['hand'] * 1e3:.1f} mm, object {sc['object'] * 1e3:.1f} mm")
    run, state, _ = kept
    if run.method is not method:  # a later draw won: ``method`` takes over its state
        method.adopt(run.method)
        run.method = method
    return run, scores, state


def fit_model(method, train_demos: list[Demo], val_demos: list[Demo] | None, progress: bool = True,
              out_dir: Path | None = None) -> TrainResult:
    """Trains ``method`` (an ours.Ours) in place; leaves it holding the best weights."""
    from tqdm import tqdm

    t0 = time.perf_counter()
    keep_best = bool(val_demos)  # else the final weights are kept, and the training starts scored once, at the end
    scored = val_demos or train_demos
    candidates: list[dict] = []
    best = {"score": np.inf, "step": 0, "state": None, "t": 0.0}
    evals: list[dict] = []
    if method.cfg.candidates > 1:
        run, candidates, state = pick_candidate(method, train_demos, scored, progress)
        if run.step == method.cfg.steps:  # the draws were compared on their final weights
            kept = dict(candidates[method.cfg.candidate], step=run.step, seconds=time.perf_counter() - t0)
            evals.append(kept)
            best = {"score": kept["score"], "step": run.step, "t": kept["seconds"], "state": state}
    else:
        run = _Training(method, train_demos)
    cfg = method.cfg
    bar = tqdm(range(run.step + 1, cfg.steps + 1), desc=f"train {cfg.name}", disable=not progress, leave=False)
    for step in bar:
        run.advance()
        if step % 50 == 0:
            bar.set_postfix(loss=f"{np.mean(method.losses[-50:]):.4f}")
        # selection rollouts (~10 s each) only once the cosine schedule has decayed: the best comes late
        if step == cfg.steps or (keep_best and step % cfg.eval_every == 0 and step >= cfg.eval_from * cfg.steps):
            sc, state = run.score(scored)
            sc["step"], sc["seconds"] = step, time.perf_counter() - t0
            evals.append(sc)
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
    method.candidate_scores = candidates
    result = TrainResult(None, best["step"], float(best["score"]), seconds, best["t"], list(method.losses), evals)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        result.checkpoint = out_dir / "policy.pt"
        method.save(str(result.checkpoint))
        (out_dir / "config.json").write_text(cfg.to_json())
        (out_dir / "train.json").write_text(json.dumps(
            {"preset": cfg.name, "train_demos": len(train_demos), "selection_demos": len(val_demos or []),
             "kept": "best on the held-out demonstrations" if keep_best else "final weights",
             "candidates": candidates, "kept_candidate": cfg.candidate,
             "best_step": best["step"], "best_score_m": result.best_score, "seconds": seconds,
             "seconds_to_best": best["t"], "evals": evals}, indent=2, default=float))
        plot_losses(np.array(method.losses), evals, out_dir / "loss.png")
    return result


def train(config, train_demos: list[Demo], val_demos: list[Demo] | None, out_dir: str | Path | None,
          progress: bool = True) -> TrainResult:
    """Trains a fresh policy (config: PolicyConfig or preset name): best on ``val_demos``, else the final weights."""
    from services.policy.ours import Ours

    method = Ours(config)
    result = fit_model(method, train_demos, val_demos, progress, Path(out_dir) if out_dir else None)
    result.method = method  # type: ignore[attr-defined]  (handy for callers; not serialized)
    return result


def plot_losses(losses: np.ndarray, evals: list[dict], path: Path) -> None:
    import matplotlib

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


def main(argv: list[str] | None = None) -> int:
    from services.policy.network import PRESETS

    parser = argparse.ArgumentParser(prog="xm train", description="Train the denoising keypoint policy of thesis "
                                     "chapter 7; writes policy.pt (torch.load(weights_only=True)), config.json, "
                                     "train.json and loss.png.")
    parser.add_argument("recordings", nargs="*", help="MCAP recordings (scene + session keys)")
    parser.add_argument("--teacher", type=int, default=None, metavar="SEED",
                        help="instead: the 15-demonstration assembly protocol of this seed (3 train, 12 validation)")
    parser.add_argument("--preset", default="multimodal", choices=sorted(PRESETS))
    parser.add_argument("--steps", type=int, default=None, help="optimizer steps (default: the preset's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="change a PolicyConfig field of the preset, e.g. --set reservoir_periods=0.25,8, or "
                        "--set candidates=2 (train two draws, keep the one whose rollouts from the selection "
                        "demonstrations score best; twice the time) (repeatable)")
    parser.add_argument("--val", type=int, default=0, help="recordings: hold out this many demonstrations")
    parser.add_argument("--threads", type=int, default=2,
                        help="torch threads (default %(default)s); 1 trains bit for bit as `xm eval` does, so "
                        "--teacher S --threads 1 gives the net of its row (1) (the thread count changes the "
                        "summation order, and with it the net)")
    parser.add_argument("--select", choices=["final", "validation"], default=None,
                        help="which weights are kept: the best on the held-out demonstrations' rollouts, or the "
                        "final (averaged) ones (default: validation where any is held out, except with --teacher: "
                        "final, as `xm eval` does, so the validation layouts stay unseen)")
    parser.add_argument("--out", default="runs/policy", help="output directory")
    args = parser.parse_args(argv)
    from services.policy.dataset import DatasetError, demos_from_mcap, split_demos
    from services.policy.network import config_changes

    try:
        changes = config_changes(args.set)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    if args.recordings:
        demos = []
        for rec in args.recordings:
            report: list[str] = []
            try:
                demos += demos_from_mcap(rec, report=report)
            except DatasetError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
            for line in report:
                print(f"warning: {line}", file=sys.stderr)
        train_d, val_d = (demos[:-args.val], demos[-args.val:]) if args.val else (demos, [])
    elif args.teacher is not None:
        from services.world.teacher import assembly_protocol

        train_d, val_d = split_demos(assembly_protocol(args.teacher))
    else:
        print("error: no demonstrations: give recordings or --teacher SEED", file=sys.stderr)
        return 2
    if not train_d:
        print("error: no training demonstrations left", file=sys.stderr)
        return 2
    torch.set_num_threads(max(1, args.threads))
    cfg = PRESETS[args.preset].replace(**changes)
    if args.steps:
        cfg = cfg.replace(steps=args.steps)
    select = args.select or ("final" if args.teacher is not None and not args.recordings else "validation")
    held_out = val_d if select == "validation" and val_d else None  # None: the final weights are kept
    res = train(cfg, train_d, held_out, args.out)
    kept = f"best at step {res.best_step}" if held_out else "final weights"
    print(f"wrote {res.checkpoint} ({len(train_d)} train demonstrations, {kept} after {res.seconds_to_best:.0f} s "
          f"of {res.seconds:.0f} s; rollout distance {res.best_score * 1e3:.1f} mm from the "
          f"{'validation' if held_out else 'training'} start states)")
    return 0
