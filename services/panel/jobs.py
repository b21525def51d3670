"""Training jobs started from the dashboard, and the trained models they leave (no viser, no Zenoh).

A job is one `xm train RECORDINGS_DIR` process (the library's splits and trims decide the data,
learning/from_library.py) in its own process group, writing into a hidden ``.NAME.partial``
directory of the models directory; its progress arrives as JSON lines in that directory
(``--progress``). Only a job that exits successfully is renamed to ``NAME``: a cancelled, failed
or interrupted job leaves no model behind, and its partial directory is removed (also any left by
a panel that was killed mid-job). ``start_first`` runs the first network of a fresh install instead
(`xm train --teacher 0`, in place into the policy service's checkpoint directory; its log in a
hidden ``.job.partial`` there). One job runs at a time: ``start`` refuses a second. The job
dies with the thread that started it (``PR_SET_PDEATHSIG``), so call ``start`` from a thread that
lives as long as the panel.
"""

from __future__ import annotations

import ctypes
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from learning.presets import PRESETS
from services.panel import executions
from services.panel.library import Entry
from shared.realtime import shift_autogroup

PARTIAL = ".partial"
ROOT = Path(__file__).resolve().parents[2]  # the job runs this tree's `xm train`
PR_SET_PDEATHSIG = 1  # prctl option (linux/prctl.h)
try:  # looked up here: between fork and exec the child only calls it
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):  # not Linux: a restarted panel still stops an orphaned job (stop_orphan)
    _PRCTL = None


class JobError(ValueError):
    """A training request refused before any process starts; the message says why."""


class JobBusyError(JobError):
    """Another training job is running."""


def check_library(entries: list[Entry]) -> tuple[int, int]:
    """(train, validation) usable demonstrations; JobError when there is nothing to train on."""
    train = sum(e.usable and e.meta.split == "train" for e in entries)
    val = sum(e.usable and e.meta.split == "validation" for e in entries)
    if not train:
        why = (f"only validation demonstrations ({val})" if val else "no usable demonstrations")
        raise JobError(f"nothing to train on: {why}; mark at least one demonstration as train in the library")
    return train, val


@dataclass
class Progress:
    """What a job has reported so far."""
    step: int = 0
    steps: int = 0
    loss: list[tuple[int, float]] = field(default_factory=list)  # (step, mean training loss)
    evals: list[tuple[int, float]] = field(default_factory=list)  # (step, validation rollout distance m)

    def add(self, record: dict) -> None:
        self.step, self.steps = int(record.get("step", self.step)), int(record.get("steps", self.steps))
        if "loss" in record:
            self.loss.append((self.step, float(record["loss"])))
        if "eval" in record:
            self.evals.append((self.step, float(record["eval"]["score"])))


@dataclass
class Job:
    name: str
    preset: str
    started: float
    process: subprocess.Popen
    partial: Path
    final: Path
    progress: Progress = field(default_factory=Progress)
    state: str = "running"  # running | done | failed | cancelled
    message: str = ""
    offset: int = 0  # bytes of the progress file read
    first: bool = False  # the first network: written in place (`final`), ``partial`` only holds its log
    cpu_share: int | None = None  # its session's autogroup nice value; None: the OS refused or has no autogroups


class Trainer:
    """The one training job of a panel, and the models directory it writes into."""

    def __init__(self, models: str | Path, extra_args: str = "", threads: int = 2, share_steps: int = 0) -> None:
        self.models = Path(models)
        self.extra_args = shlex.split(extra_args)
        self.threads = threads
        self.share_steps = share_steps
        self.job: Job | None = None
        self._lock = threading.Lock()
        self.remove_partials()

    def remove_partials(self) -> None:
        """Partial directories of jobs that did not finish (a killed panel), unless one is running;
        a job a killed panel left running is stopped first (its pid file names it)."""
        if self.models.is_dir():
            for p in self.models.glob(f".*{PARTIAL}"):
                if self.job is None or p != self.job.partial:
                    stop_orphan(p)
                    shutil.rmtree(p, ignore_errors=True)

    @property
    def running(self) -> bool:
        return self.job is not None and self.job.state == "running"

    def start(self, recordings: Path, preset: str, steps: int = 0) -> Job:
        """Start `xm train recordings`; JobBusyError while a job runs, JobError for a bad request."""
        if steps < 0:
            raise JobError(f"steps must be >= 0 (0: the preset's), got {steps}")
        return self._launch(preset, lambda partial: [str(recordings.resolve()), "--out", str(partial),
                                                     *(["--steps", str(steps)] if steps else [])])

    def start_first(self, checkpoint: Path, preset: str, steps: int = 0, teacher: int = 0) -> Job:
        """The first network of a fresh install: `xm train --teacher SEED --out DIR [--steps N]` into the
        directory of the checkpoint the policy service waits for. `xm train` writes the demonstrations
        there first (the policy's naive fallback replays them meanwhile) and the checkpoint last, in one
        rename. ``steps`` 0: the preset's budget."""
        out = checkpoint.parent
        if checkpoint.name != "policy.pt":
            raise JobError(f"first network: `xm train` writes policy.pt, the policy service waits for {checkpoint}")
        if steps < 0:
            raise JobError(f"first network: steps must be >= 0 (0: the preset's), got {steps}")
        return self._launch(preset, lambda _partial: ["--teacher", str(teacher), "--out", str(out),
                                                      *(["--steps", str(steps)] if steps else [])],
                            final=out, name=f"first-network-{preset}")

    def _launch(self, preset: str, args: Callable[[Path], list[str]], final: Path | None = None,
                name: str = "") -> Job:
        if preset not in PRESETS:
            raise JobError(f"unknown preset {preset!r}; known: {', '.join(sorted(PRESETS))}")
        if not self._lock.acquire(blocking=False):
            raise JobBusyError("a training job is being started")
        try:
            if self.running:
                job = self.job
                raise JobBusyError(f"a training job is running: {job.name} (started "
                                   f"{time.strftime('%H:%M:%S', time.localtime(job.started))}); cancel it first")
            first = final is not None
            if final is None:
                name = f"{time.strftime('%Y%m%d-%H%M%S')}-{preset}"
                final = self.models / name
                n = 2
                while final.exists():
                    final = self.models / f"{name}-{n}"
                    n += 1
                name = final.name
            partial = (final / f".job{PARTIAL}") if first else self.models / f".{final.name}{PARTIAL}"
            stop_orphan(partial)  # a first network a killed panel left running
            shutil.rmtree(partial, ignore_errors=True)  # and its log
            partial.mkdir(parents=True)
            cmd = [sys.executable, "-m", "shared.cli", "train", *args(partial), "--preset", preset,
                   "--threads", str(self.threads), "--progress", str(partial / "progress.jsonl"), *self.extra_args]
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(ROOT),
                                                                             os.environ.get("PYTHONPATH"))))}
            with (partial / "train.log").open("wb") as log:
                proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                        start_new_session=True,  # its own group: cancel stops all of it
                                        preexec_fn=_die_with_parent)
            (partial / "job.pid").write_text(str(proc.pid))
            # Linux schedules each session as one group, and every service is a session of its own: a
            # job left at its group's default gets one service's share, a tenth of the host beside the cell.
            share = shift_autogroup(proc.pid, -self.share_steps) if self.share_steps else None
            self.job = Job(name, preset, time.time(), proc, partial, final, first=first, cpu_share=share)
            return self.job
        finally:
            self._lock.release()

    def poll(self) -> Job | None:
        """Read new progress; when the process has ended, keep its model (exit 0) or remove it."""
        with self._lock:
            job = self.job
            if job is None or job.state != "running":
                return job
            self._read(job)
            code = job.process.poll()
            if code is None:
                return job
            self._read(job)
            if job.first:  # in place: the checkpoint is whole (written by one rename) or absent
                if code == 0 and (job.final / "policy.pt").exists():
                    job.state, job.message = "done", f"wrote {job.final / 'policy.pt'}"
                    shutil.rmtree(job.partial, ignore_errors=True)
                else:  # its log stays for a look (`train.log`); the next start replaces it
                    job.state, job.message = "failed", self._error(job, code)
            elif code == 0 and (job.partial / "policy.pt").exists():
                os.replace(job.partial, job.final)  # the model appears whole, or not at all
                job.state, job.message = "done", f"wrote {job.final}"
            else:
                job.state, job.message = "failed", self._error(job, code)
                shutil.rmtree(job.partial, ignore_errors=True)
            return job

    def cancel(self) -> bool:
        """Kill the running job's process group and remove its partial model (nothing of a cancelled
        job is kept, so it needs no chance to finish anything)."""
        with self._lock:
            job = self.job
            if job is None or job.state != "running":
                return False
            try:
                os.killpg(job.process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            job.process.wait()
            shutil.rmtree(job.partial, ignore_errors=True)  # (a first network's log; its checkpoint is not written)
            job.state, job.message = "cancelled", "cancelled; no model written"
            return True

    @staticmethod
    def _read(job: Job) -> None:
        path = job.partial / "progress.jsonl"
        try:
            with path.open("rb") as f:
                f.seek(job.offset)
                data = f.read()
        except OSError:
            return
        end = data.rfind(b"\n") + 1  # a line still being written is read next time
        job.offset += end
        for line in data[:end].splitlines():
            try:
                job.progress.add(json.loads(line))
            except (ValueError, KeyError, TypeError):
                continue

    @staticmethod
    def _error(job: Job, code: int) -> str:
        """The job's own error line (`xm train` prints "error: ..."), else its last output line."""
        try:
            lines = (job.partial / "train.log").read_text(errors="replace").splitlines()
        except OSError:
            lines = []
        errors = [ln for ln in lines if ln.startswith("error:")]
        last = errors[-1] if errors else (lines[-1] if lines else "")
        return f"failed (exit code {code}): {last[:300]}"


def _die_with_parent() -> None:
    """In the job's process before exec: killed when the thread that started it ends (the panel
    starts jobs from one thread that lives as long as the panel), so a killed panel leaves no job."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)


def stop_orphan(partial: Path) -> None:
    """Kill the process group of the job writing into ``partial``, if it still runs (its command
    line names the directory, so a reused pid is left alone)."""
    try:
        pid = int((partial / "job.pid").read_text())
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except (OSError, ValueError):
        return
    if str(partial).encode() in cmdline:
        try:
            os.killpg(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@dataclass
class Model:
    """A trained model in the models directory, described by its train.json."""
    name: str
    checkpoint: Path
    preset: str
    date: str
    train_demos: int
    validation_demos: int
    score_mm: float | None  # best validation rollout distance (hand + object)
    data: list[str]  # the recordings it was trained on (split in brackets)
    executions: str = "-"  # its logged executions (executions.jsonl beside it): "2 / 3 succeeded"


def models(directory: str | Path) -> list[Model]:
    """Finished models, newest first (a hidden partial directory is never listed)."""
    out = []
    directory = Path(directory)
    if not directory.is_dir():
        return out
    for d in directory.iterdir():
        ckpt = d / "policy.pt"
        if d.name.startswith(".") or not ckpt.is_file():
            continue
        try:
            info = json.loads((d / "train.json").read_text())
        except (OSError, ValueError):
            info = {}
        score = info.get("best_score_m")
        out.append(Model(d.name, ckpt, str(info.get("preset", "?")),
                         time.strftime("%Y-%m-%d %H:%M", time.localtime(ckpt.stat().st_mtime)),
                         int(info.get("train_demos", 0)), int(info.get("selection_demos", 0)),
                         None if not isinstance(score, (int, float)) or score != score or score == float("inf")
                         else score * 1e3,
                         [f"{u.get('name')} ({u.get('split')})" for u in info.get("data", []) if isinstance(u, dict)],
                         executions.summary(executions.read(d / executions.LOG_NAME)[0])))
    return sorted(out, key=lambda m: m.checkpoint.stat().st_mtime, reverse=True)


def models_table(items: list[Model], serving: str | None = None) -> str:
    """The model list as markdown: name, preset, demonstrations, score, date, data."""
    if not items:
        return "no trained models yet"
    rows = ["| model | preset | train / val | score mm | executions | date | data |", "|---|---|---|---|---|---|---|"]
    for m in items:
        name = f"**{m.name}** (serving)" if serving and str(m.checkpoint) == serving else m.name
        score = "-" if m.score_mm is None else f"{m.score_mm:.1f}"
        rows.append(f"| {name} | {m.preset} | {m.train_demos} / {m.validation_demos} | {score} | {m.executions} | "
                    f"{m.date} | "
                    f"{', '.join(m.data) or '-'} |")
    return "\n".join(rows)
