"""When to try a lost camera again, and what to report about it (pure: times are passed in).

A camera that fails to open or to deliver a frame is marked missing; the rig keeps triggering the
others and tries this one again after a back-off that doubles up to a ceiling, so a device that
was unplugged comes back within seconds of being plugged in without the rig spending its frame
time on open calls.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class CameraState:
    name: str
    first_retry_s: float = 0.5
    max_retry_s: float = 5.0
    open: bool = False
    frames: int = 0  # frames delivered
    gaps: int = 0  # frame sets this camera missed
    losses: int = 0  # times it went from delivering to missing
    reopened: int = 0  # times it came back after a loss
    error: str = ""
    retry_at: float = 0.0
    _delay: float = field(default=0.0, repr=False)

    def due(self, now: float) -> bool:
        """Whether a closed camera should be opened now."""
        return not self.open and now >= self.retry_at

    def opened(self) -> None:
        if self.losses:
            self.reopened += 1
        self.open, self.error, self._delay = True, "", 0.0

    def failed(self, now: float, error: str) -> None:
        """An open or a read failed: closed until the back-off has passed."""
        if self.open:
            self.losses += 1
        self.open, self.error = False, error
        self._delay = self.first_retry_s if self._delay == 0.0 else min(2 * self._delay, self.max_retry_s)
        self.retry_at = now + self._delay

    def delivered(self) -> None:
        self.frames += 1

    def missed(self) -> None:
        self.gaps += 1

    def report(self) -> dict:
        return {"status": "ok" if self.open else "missing", "frames": self.frames, "gaps": self.gaps,
                "losses": self.losses, "reopened": self.reopened, "error": self.error}
