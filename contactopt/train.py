"""Training loop shared by `xm contactopt train` and the optimizer comparison."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch
from tqdm import tqdm

from contactopt.losses3d import loss_breakdown3d, make_policy, residual_fn3d, sdf_object
from contactopt.objective import Objective, flat_params, loss_breakdown, residual_fn
from contactopt.optim import FirstOrder, GaussNewton
from contactopt.policy import Policy
from contactopt.replay import replay3d, replay_planar
from contactopt.sim import World, object_sdf, rollout
from contactopt.sim3d import scene
from contactopt.tasks import Task, batch_positions, success, turn_velocity
from contactopt.tasks3d import Task3D, success3d, task_metric

EVAL_SEED = 10_000  # evaluation batches come from a seed no training run uses
OPTIMIZERS = ("gn", "sgd", "adam")


@dataclass
class Result:
    task: str
    optimizer: str
    lr: float | None
    iterations: int = 0
    seconds: float = 0.0
    clock: str = "wall"  # what `seconds` and the curve's times count: "wall" or "cpu" seconds
    curve: list[tuple[float, float]] = field(default_factory=list)  # (seconds, batch loss)
    counters: dict[str, int] = field(default_factory=dict)
    evaluation: dict[str, float] = field(default_factory=dict)
    success: bool = False
    replay_success: bool = False  # the metric's criterion met in the MuJoCo replay too


def make_optimizer(name: str, lr: float | None) -> GaussNewton | FirstOrder:
    if name == "gn":
        return GaussNewton()
    if name in ("sgd", "adam"):
        if lr is None:
            raise ValueError(f"{name} needs a learning rate")
        return FirstOrder(name, lr)
    raise ValueError(f"unknown optimizer {name!r}; optimizers: {', '.join(OPTIMIZERS)}")


def evaluate(policy: Policy, task: Task, batch: int = 32) -> dict[str, float]:
    """Mean turn velocity under the predicted contacts, the losses, the turn velocity when the
    policy's joint commands are replayed with the simulator's own hard and softplus contacts,
    and the MuJoCo replay of the predicted forces (plausibility)."""
    pos = batch_positions(task, batch, EVAL_SEED, 0)
    obj = Objective(task)
    out = loss_breakdown(policy, obj, pos)
    with torch.no_grad():
        ro = rollout(policy, task, pos, "predicted")
        out["turn_velocity"] = float(turn_velocity(ro.theta0, ro.theta[:, -1], task).mean())
        s = ro.steps
        d_obj, _ = object_sdf(s.tips, s.pos, s.theta, task)
        weight = s.force.norm(dim=-1)  # the fingertip-object gap where the predicted forces act
        out["force_weighted_gap_mm"] = float(1000 * ((d_obj - World().tip_radius) * weight).sum() / weight.sum())
        for model, key in (("hard", "replay_turn_velocity"), ("softplus", "replay_softplus_turn_velocity")):
            rh = rollout(policy, task, pos, model)
            out[key] = float(turn_velocity(rh.theta0, rh.theta[:, -1], task).mean())
        b, t = ro.theta.shape[0], ro.theta.shape[1] - 1
        out.update(replay_planar(task, ro.pos, ro.theta, s.force.reshape(b, t, 2, 2),
                                 (0.5 * (s.p_a + s.p_b)).reshape(b, t, 2, 2), World().table_mu))
    out.update(metric=out["turn_velocity"], goal=task.omega_goal, drift=0.0)
    return out


def evaluate3d(policy: Policy, task: Task3D, batch: int = 32) -> dict[str, float]:
    """The success metric under the predicted contacts, the losses, the fingertip-object gap
    where the predicted forces act, and the MuJoCo replay of the predicted fingertip forces."""
    out, ro = loss_breakdown3d(policy, task, batch_positions(task, batch, EVAL_SEED, 0))
    out.update(task_metric(task, ro.pos, ro.omega))
    s = ro.steps
    n_tips = len(scene(task.robot).chain.sphere_names)
    d_tip, _ = sdf_object(s.anchor_a[:, :n_tips], s.pos, s.rot, task)
    gap = d_tip - scene(task.robot).chain.sphere_radius
    weight = s.force[:, :n_tips].norm(dim=-1)
    out["force_weighted_gap_mm"] = float(1000 * (gap * weight).sum() / weight.sum())
    out.update(replay3d(task, ro, n_tips))
    return out


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def train(task: Task | Task3D, optimizer: str = "gn", lr: float | None = None, budget_s: float = 600.0,
          batch: int = 16, seed: int = 0, max_iterations: int | None = None,
          progress: bool = True, clock: str = "wall") -> tuple[Policy, Result]:
    """Optimize a fresh contact-based policy (seeded) on batch k = batch_positions(seed, k) at
    iteration k until the budget (training time only) or max_iterations is spent. `clock`: "wall"
    (wall-clock seconds) or "cpu" (this process's CPU seconds: the same compute for every run
    on a shared, loaded host, where wall-clock time measures the other work as much as this)."""
    torch.manual_seed(seed)
    three_d = isinstance(task, Task3D)
    policy = make_policy(task) if three_d else Policy()
    obj = None if three_d else Objective(task)
    w, unflatten = flat_params(policy)
    opt = make_optimizer(optimizer, lr)
    result = Result(task.name, optimizer, lr)
    bar = tqdm(total=int(budget_s), unit="s", disable=not progress, desc=f"{task.name} {optimizer}")
    if clock not in CLOCKS:
        raise ValueError(f"unknown clock {clock!r}; clocks: {', '.join(CLOCKS)}")
    now = CLOCKS[clock]
    start = now()
    k = 0
    while now() - start < budget_s and (max_iterations is None or k < max_iterations):
        xy = batch_positions(task, batch, seed, k)
        fn = residual_fn3d(policy, task, xy, unflatten) if obj is None else residual_fn(policy, obj, xy)
        w, loss = opt.step(fn, w)
        k += 1
        elapsed = now() - start
        result.curve.append((elapsed, loss))
        bar.n = min(int(elapsed), int(budget_s))
        bar.set_postfix(loss=f"{loss:.4g}")
        bar.refresh()
    bar.close()
    result.iterations, result.seconds, result.clock = k, now() - start, clock
    result.counters = dict(opt.counters)
    with torch.no_grad():
        for p, v in zip(policy.parameters(), unflatten(w).values(), strict=True):
            p.copy_(v)
    if three_d:
        result.evaluation = evaluate3d(policy, task)
        result.success = success3d(task, result.evaluation) and result.evaluation["distance"] < 1.0
    else:
        result.evaluation = evaluate(policy, task)
        result.success = success(result.evaluation["turn_velocity"], task) and result.evaluation["distance"] < 1.0
    # the success criterion's metric as MuJoCo reproduces it from the predicted forces
    ev = result.evaluation
    result.replay_success = bool(abs(ev["replay_metric"] - ev["goal"]) <= task.success_tolerance * abs(ev["goal"]))
    return policy, result


def plot_curves(results: list[Result], path: str) -> None:
    """Learning curves (batch loss against training seconds) as a PNG."""
    import matplotlib  # optional heavy dependency, only for the figure
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for r in results:
        label = r.optimizer if r.lr is None else f"{r.optimizer} lr={r.lr:g}"
        ax.plot([t for t, _ in r.curve], [loss for _, loss in r.curve], label=label)
    ax.set_yscale("log")
    ax.set_ylim(top=1e4)  # diverging runs would otherwise hide the others
    ax.set_xlabel(f"training time [{results[0].clock if results else 'wall'} s]")
    ax.set_ylabel("batch loss (task + consistency)")
    ax.set_title(results[0].task if results else "")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
