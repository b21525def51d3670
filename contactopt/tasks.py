"""Tasks 1-2 of thesis Table 2.1: two fingers turn a cube or a cylinder about the vertical axis
(tasks 3-8, the hand tasks, are in `tasks3d`; `get_task` finds either).

Task loss (thesis 2.3): the squared difference between the object's average angular velocity
over the episode and the goal velocity. Object positions are randomized in X and Y with a
Gaussian. Success: the average turn velocity of the evaluation episodes is within 20 % of the goal.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from contactopt.tasks3d import TASKS3D, Task3D


@dataclass(frozen=True)
class Task:
    name: str
    shape: str             # "box" (a cube seen from above) or "cylinder" (upright: a circle)
    size: float            # half side of the cube or radius of the cylinder [m]
    omega_goal: float      # goal angular velocity about the vertical axis [rad/s], counterclockwise
    steps: int = 20        # episode length
    dt: float = 0.025      # semi-implicit Euler step [s]
    position_sigma: float = 0.005  # Gaussian noise of the object's X and Y [m]
    success_tolerance: float = 0.2  # relative error of the average turn velocity


TASKS: dict[str, Task] = {
    "turn_cube": Task("turn_cube", "box", 0.03, 1.0),
    "turn_cylinder": Task("turn_cylinder", "cylinder", 0.03, 1.0),
}


ALL_TASKS = (*TASKS, *TASKS3D)  # in the order of thesis Table 2.1


def get_task(name: str) -> Task | Task3D:
    """The task called `name`; a ValueError lists the tasks that exist."""
    if name in TASKS:
        return TASKS[name]
    if name in TASKS3D:
        return TASKS3D[name]
    raise ValueError(f"unknown task {name!r}; tasks: {', '.join(ALL_TASKS)}")


def sample_positions(task: Task | Task3D, batch: int, generator: torch.Generator) -> torch.Tensor:
    """(batch, 2) initial object positions: the origin plus Gaussian noise in X and Y."""
    return task.position_sigma * torch.randn(batch, 2, generator=generator, dtype=torch.float64)


def batch_positions(task: Task | Task3D, batch: int, seed: int, index: int) -> torch.Tensor:
    """Batch number `index` of a seeded sequence, so optimizers compared see the same batches."""
    g = torch.Generator().manual_seed(seed * 1_000_003 + index)
    return sample_positions(task, batch, g)


def turn_velocity(theta0: torch.Tensor, theta_end: torch.Tensor, task: Task) -> torch.Tensor:
    """Average angular velocity of each episode."""
    return (theta_end - theta0) / (task.steps * task.dt)


def task_residual(theta0: torch.Tensor, theta_end: torch.Tensor, task: Task) -> torch.Tensor:
    """Residual whose square is the task loss, relative to the goal velocity."""
    return (turn_velocity(theta0, theta_end, task) - task.omega_goal) / abs(task.omega_goal)


def success(mean_velocity: float, task: Task) -> bool:
    """The task's success criterion on the mean turn velocity of evaluation episodes."""
    return abs(mean_velocity - task.omega_goal) <= task.success_tolerance * abs(task.omega_goal)
