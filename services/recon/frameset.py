"""Collects per-camera images into frame sets by trigger stamp (pure).

camhub stamps every camera of a frame set with the same trigger time. A set is complete when every
expected camera has delivered; a set still incomplete when ``late_after`` newer sets have begun is
released with the cameras it has (a camera missing or late: the others still reconstruct it).
Items of several kinds per camera (``cam0`` and ``cam0/info``: an image and its CameraInfo) may
arrive through separate subscriptions, one kind running frame sets ahead of the other; a newer
set counts toward another's lateness only once it holds an item of every kind.
A stamp more than ``restart_s`` before every set already released is a new timeline (the
simulated clock restarts with the world): the buffer starts over rather than call it late.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class FrameSetBuffer:
    late_after: int = 1
    max_sets: int = 8
    restart_s: float = 2.0
    pending: dict = field(default_factory=dict)  # stamp -> {camera: payload}
    released_partial: int = 0
    dropped_stale: int = 0
    restarts: int = 0
    _done: set = field(default_factory=set)

    def add(self, stamp: float, camera: str, payload: object, expected: set[str]) -> list[tuple[float, dict]]:
        """Adds one camera's image; returns the frame sets (stamp, {camera: payload}) now ready,
        oldest first."""
        if self._done and stamp < min(self._done) - self.restart_s:
            self.pending.clear()
            self._done.clear()
            self.restarts += 1
        if stamp in self._done or (self._done and stamp < min(self._done)):
            self.dropped_stale += 1  # a camera later than its set's release
            return []
        self.pending.setdefault(stamp, {})[camera] = payload
        ready = []
        stamps = sorted(self.pending)
        kinds = {_kind(e) for e in expected}
        begun = [kinds <= {_kind(k) for k in self.pending[s]} for s in stamps]
        for i, s in enumerate(stamps):
            got = self.pending[s]
            newer = sum(begun[i + 1:])
            if expected and expected <= set(got):
                ready.append(s)
            elif newer >= self.late_after or len(stamps) > self.max_sets:
                ready.append(s)
                self.released_partial += 1
        out = []
        for s in ready:
            out.append((s, self.pending.pop(s)))
            self._done.add(s)
        while len(self._done) > self.max_sets:
            self._done.discard(min(self._done))
        return out

    @property
    def released(self) -> bool:
        """Whether a frame set of the current timeline has been released."""
        return bool(self._done)

    def flush(self) -> list[tuple[float, dict]]:
        """Every pending frame set, oldest first (the end of a recording)."""
        out = [(s, self.pending.pop(s)) for s in sorted(self.pending)]
        self._done.update(s for s, _ in out)
        return out


def _kind(item: str) -> str:
    """``cam0`` -> "", ``cam0/info`` -> "info"."""
    return item.partition("/")[2]
