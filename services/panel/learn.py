"""The dashboard's Learn folder: train on the library from the page, follow the job, list the models.

Train starts an `xm train` process on the library (services/panel/jobs.py); a monitor thread of
its own (never the panel's event loop) reads the job's progress twice a second and updates the
progress line, the loss curve and the validation score, and re-reads the models directory. The
folder is shared by every connected browser: a browser pressing Train while a job runs is told so
in a notification of its own.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import viser
from viser import uplot

from learning.presets import PRESETS
from services.panel.jobs import JobBusyError, JobError, Model, Trainer, check_library, models, models_table
from services.panel.library import Entry

log = logging.getLogger("xm")
POLL_S = 0.5  # progress refresh
MODELS_EVERY = 10  # polls between rescans of the models directory while no job runs


class Learn:
    """``entries()`` the library as last scanned; ``serving()`` the checkpoint path the policy serves
    (or None); ``count`` the @health error counter."""

    def __init__(self, server: viser.ViserServer, recordings: Path, trainer: Trainer,
                 entries: Callable[[], list[Entry]], serving: Callable[[], str | None],
                 count: Callable[[str], None]) -> None:
        self.server = server
        self.recordings = recordings
        self.trainer = trainer
        self.entries = entries
        self.serving = serving
        self.count = count
        self.models: list[Model] = []
        self.on_models: list[Callable[[list[Model]], None]] = []  # told when the model list changes
        self._plots: dict[str, Any] = {}
        self._drawn = (-1, -1)  # (loss points, eval points) on the plots
        self._stop = threading.Event()
        # jobs start from this one thread: a job dies with the thread that started it (jobs.py)
        self._starter = ThreadPoolExecutor(max_workers=1, thread_name_prefix="panel-train-start")
        self._build()
        self._thread = threading.Thread(target=self._monitor, name="panel-training", daemon=True)
        self._thread.start()

    def _build(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Learn") as self.folder:
            gui.add_markdown("Trains on the library: the demonstrations marked train, scored on those marked "
                             "validation, each within its trim.")
            self.preset = gui.add_dropdown("preset", tuple(sorted(PRESETS)), initial_value="multimodal")
            self.steps = gui.add_number("steps", initial_value=0, min=0, step=1, hint="0: the preset's")
            gui.add_button("Train", color="green").on_click(self._train)
            gui.add_button("Cancel training").on_click(lambda _e: self._cancel())
            self.job_md = gui.add_markdown("no training job")
            self.models_md = gui.add_markdown("reading the models directory...")

    # --- buttons (viser worker threads) ----------------------------------------------------------
    def _train(self, event: Any) -> None:
        try:
            n_train, n_val = check_library(self.entries())
            job = self._starter.submit(self.trainer.start, self.recordings, self.preset.value,
                                       int(self.steps.value or 0)).result()
        except JobError as exc:
            busy = isinstance(exc, JobBusyError)
            self.count("train_busy" if busy else "train_refused")
            if not busy:  # the shared line shows the running job; only the presser hears of the refusal
                self.job_md.content = f"**refused**: {exc}"
            if event.client is not None:
                event.client.add_notification("Train refused", str(exc), color="red", auto_close_seconds=10.0)
            return
        except OSError as exc:  # the models directory cannot be written
            self.count("train_error")
            self.job_md.content = f"**error**: cannot start training: {exc}"
            return
        self._clear_plots()
        self.job_md.content = (f"training **{job.name}** on {n_train} train and {n_val} validation recordings: "
                               "starting...")

    def start_first(self, checkpoint: Path, preset: str, steps: int = 0) -> None:
        """The first network of a fresh install (the checkpoint the policy service waits for), trained
        from the world's scripted teacher as the page's job when it is missing or does not load (one
        of other configs), in ``steps`` optimizer steps (0: the preset's); a failure is shown in the job line."""
        def start() -> None:
            problem = checkpoint_problem(checkpoint)
            if not problem:
                return
            log.info("training the first network: %s", problem)
            try:
                job = self.trainer.start_first(checkpoint, preset, steps)
            except (JobError, OSError) as exc:
                self.count("train_refused")
                self.job_md.content = f"**first network not started**: {exc}"
                return
            self.job_md.content = (f"training the first network **{job.name}** into `{checkpoint}` from the "
                                   "scripted teacher; the cell runs on the naive fallback meanwhile: starting...")
        self._starter.submit(start)

    def _cancel(self) -> None:
        if self.trainer.cancel():
            self.job_md.content = f"{self.trainer.job.name}: {self.trainer.job.message}"

    # --- monitor thread ----------------------------------------------------------------------
    def _monitor(self) -> None:
        polls = 0
        while not self._stop.wait(POLL_S):
            try:
                was_running = self.trainer.running
                job = self.trainer.poll()
                if job is not None and (was_running or job.state == "running"):
                    self._show(job)
                if polls % MODELS_EVERY == 0 or (was_running and not self.trainer.running):
                    self._scan_models()
            except Exception as exc:  # the page must keep its monitor; say what went wrong
                self.count("train_monitor_error")
                log.warning("training monitor: %r", exc, exc_info=exc)
            polls += 1

    def _show(self, job: Any) -> None:
        p = job.progress
        if job.state == "running":
            line = f"training **{job.name}** ({job.preset}): step {p.step} / {p.steps or '?'}"
        else:
            line = f"**{job.name}** {job.state}: {job.message}"
        if job.first:
            line += ("; the policy service switches to it once it is written" if job.state == "running" else
                     "; the policy service loads it now (Execute: policy)" if job.state == "done" else "")
        if p.loss:
            line += f", loss {p.loss[-1][1]:.4g}"
        if p.evals:
            line += f", validation {p.evals[-1][1] * 1e3:.1f} mm (best {min(e for _, e in p.evals) * 1e3:.1f})"
        if self.job_md.content != line:
            self.job_md.content = line
        if (len(p.loss), len(p.evals)) != self._drawn:
            self._drawn = (len(p.loss), len(p.evals))
            self._plot("loss", "training loss", p.loss, 1.0, "#1e64dc")
            self._plot("score", "validation rollout distance (mm)", p.evals, 1e3, "#dc2828")

    def _plot(self, name: str, title: str, points: list[tuple[int, float]], scale: float, color: str) -> None:
        if not points:
            return
        x = np.array([s for s, _ in points], np.float64)
        y = np.array([v for _, v in points], np.float64) * scale
        plot = self._plots.get(name)
        if plot is not None:
            plot.data = (x, y)
            return
        with self.folder:
            self._plots[name] = self.server.gui.add_uplot(
                (x, y), (uplot.Series(label="step"), uplot.Series(label=title, stroke=color, width=1.5)),
                title=title, scales={"x": {"time": False}}, aspect=2.0, order=self.job_md.order + 0.01)

    def _clear_plots(self) -> None:
        for plot in self._plots.values():
            plot.remove()
        self._plots.clear()
        self._drawn = (-1, -1)

    def _scan_models(self) -> None:
        found = models(self.trainer.models)
        text = models_table(found, self.serving())
        if self.models_md.content != text:
            self.models_md.content = text
        if [m.name for m in found] != [m.name for m in self.models]:
            self.models = found
            for listener in self.on_models:
                listener(found)

    def health(self) -> dict:
        job = self.trainer.job
        return {"models": len(self.models),
                "training": None if job is None else {"name": job.name, "state": job.state, "step": job.progress.step,
                                                      "steps": job.progress.steps, "message": job.message,
                                                      "cpu_share": job.cpu_share}}

    def close(self) -> None:
        self._stop.set()
        self.trainer.cancel()
        self._starter.shutdown(wait=False)


def checkpoint_problem(path: Path) -> str:
    """Why the policy service cannot serve ``path`` ("" when it loads)."""
    if not path.exists():
        return f"{path} is missing"
    from services.policy.model import Policy  # torch: an optional heavy import, only when a checkpoint is there
    try:
        Policy.load(str(path))
    except Exception as exc:  # torch raises unrelated types for files that are no checkpoint
        return f"{path} does not load ({type(exc).__name__}: {str(exc)[:200]})"
    return ""
