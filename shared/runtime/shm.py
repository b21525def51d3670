"""Large payloads through Zenoh's shared memory between the processes of one host.

A typed publisher puts a payload of ``MIN_BYTES`` or more (camera frames, raw tactile) from a
buffer of the process's one pool, created on the first such put; a subscriber on the same host
reads it from the pool without the payload passing through the router's sockets. Sessions
negotiate shared memory per link (shared/runtime/zsession.py), so a subscriber on another host
gets the same payload copied over the network, with nothing to do here. When the pool cannot be
created or is full, the payload goes out as bytes, counted per key as ``shm_unavailable`` or
``shm_exhausted``; the pool counts its puts and these fallbacks for the process too (``shm`` in
a node's @health).

Zenoh keeps a pool mapped in every process that received from it, and in the router, for their
lifetime, also after its publisher exits (eclipse-zenoh/zenoh#2787): each restart of a publisher
that used its pool adds ``POOL_BYTES`` plus Zenoh's 1.25 MB of metadata to those processes'
memory. So only the sensor streams have a pool (``POOL_TYPES``: camera images, raw tactile), and it
is small: a few dozen frames in flight. A derived message that happens to be large (recon's
tactile mesh) goes as bytes: its publisher restarts with recon, and each recon restart
would otherwise add about 11 MB to the recorder, the panel and every other subscriber.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter

import zenoh
from zenoh.shm import GarbageCollect, ShmProvider, ZShmMut

MIN_BYTES = 64 * 1024  # below this a copy through the router costs about what the pool's bookkeeping does
POOL_BYTES = 8 << 20  # the pool per process: ~27 camera frames of 300 kB in flight
POOL_TYPES = frozenset({"sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image", "xm_msgs/msg/TactileRaw"})

log = logging.getLogger("xm")


class Pool:
    """The process's shared-memory pool, opened on first use; ``None`` from ``buffer``: send bytes."""

    def __init__(self, size: int = POOL_BYTES) -> None:
        self.size = size
        self._provider: ShmProvider | None = None
        self._failed = ""
        self._lock = threading.Lock()
        self.sent = 0  # payloads put from the pool
        self.fallbacks: Counter[str] = Counter()  # payloads copied instead, by reason

    @property
    def failed(self) -> str:
        """Why the pool could not be opened ("" when it could or was not tried)."""
        return self._failed

    def _open(self) -> ShmProvider | None:
        with self._lock:
            if self._provider is None and not self._failed:
                try:
                    self._provider = ShmProvider.default_backend(self.size)
                except zenoh.ZError as exc:  # no /dev/shm, or too small for the pool
                    self._failed = str(exc) or "unavailable"
                    log.warning("shared memory unavailable, large payloads are copied: %s", exc)
            return self._provider

    def buffer(self, pieces: list, size: int) -> tuple[ZShmMut | None, str]:
        """A pool buffer holding the concatenated ``pieces`` (``size`` bytes), or (None, why not)."""
        provider = self._provider or self._open()
        if provider is None:
            return self._fallback("shm_unavailable")
        try:
            buf = provider.alloc(size, policy=GarbageCollect())
        except zenoh.ZError:  # every buffer still held by subscribers: copies until they let go
            return self._fallback("shm_exhausted")
        buf[0:size] = pieces[0] if len(pieces) == 1 else b"".join(pieces)
        with self._lock:
            self.sent += 1
        return buf, ""

    def _fallback(self, why: str) -> tuple[None, str]:
        with self._lock:
            self.fallbacks[why] += 1
        return None, why

    def report(self) -> dict:
        """What @health shows: the pool's state, its puts and the copies made instead, by reason."""
        with self._lock:
            state = "unavailable" if self._failed else "open" if self._provider is not None else "unused"
            return {"pool": state, "pool_bytes": self.size, "sent": self.sent, "fallbacks": dict(self.fallbacks),
                    **({"unavailable": self._failed} if self._failed else {})}


POOL = Pool()
