"""Training data from a demonstration library (a recordings directory with ``NAME.demo.json``
sidecars, services/panel/library.py): the teacher's split decides which recordings train and which
validate, excluded and unusable recordings are left out with the reason, and each recording's trim
keeps only the scenes inside it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from learning.dataset import DatasetError, demos_from_mcap
from services.panel.library import Library
from shared.demo import Demo


@dataclass
class LibraryData:
    train: list[Demo] = field(default_factory=list)
    validation: list[Demo] = field(default_factory=list)
    used: list[dict] = field(default_factory=list)  # per recording used: name, split, label, trim, demonstrations
    report: list[str] = field(default_factory=list)  # what was left out, and why


def library_data(directory: str | Path) -> LibraryData:
    """The demonstrations of the library in ``directory`` by split."""
    out = LibraryData()
    for e in Library(directory).scan():
        if e.meta.split == "excluded":
            out.report.append(f"{e.name}: excluded in the library")
            continue
        if e.problems:
            out.report.append(f"{e.name}: not trainable: {'; '.join(e.problems)}")
            continue
        window = e.meta.window(e.info.duration_s)
        try:
            demos = demos_from_mcap(e.path, report=out.report, window_s=window)
        except DatasetError as exc:
            out.report.append(str(exc))
            continue
        for d in demos:
            d.meta.update(split=e.meta.split, recording=e.name)
        (out.train if e.meta.split == "train" else out.validation).extend(demos)
        out.used.append({"name": e.name, "split": e.meta.split, "label": e.meta.label,
                         "trim_s": [round(window[0], 3), round(window[1], 3)], "demonstrations": len(demos)})
    return out
