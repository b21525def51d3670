"""The one error type of the skin tools, with a counter per reason (bad input never crashes a run)."""

from __future__ import annotations

from collections import Counter

COUNTS: Counter[str] = Counter()  # reason -> how many times it was raised in this process


class SkinError(ValueError):
    """Bad input: an open or non-manifold mesh, a layout that does not fit, a part that cannot be
    nested. ``part`` names what was wrong, ``reason`` is a short key counted in COUNTS."""

    def __init__(self, reason: str, part: str, message: str) -> None:
        super().__init__(f"{part}: {message}")
        self.reason, self.part = reason, part
        COUNTS[reason] += 1
