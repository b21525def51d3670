"""Frame layer shared by the device protocols (tactile readout, robot board).

    sync (2 B: A5 5A) | type (1 B) | length (2 B LE, payload only) | payload | CRC-32 (4 B LE)

The CRC (zlib/IEEE 802.3 polynomial) covers type, length and payload. The decoder never raises:
it hunts for the sync word, rejects oversize lengths and bad CRCs, counts every byte it throws
away, and recovers the next good frame after any garbage.
"""

from __future__ import annotations

import struct
import zlib

SYNC = b"\xa5\x5a"
HEADER = struct.Struct("<2sBH")
CRC = struct.Struct("<I")
OVERHEAD = HEADER.size + CRC.size


def frame(kind: int, payload: bytes) -> bytes:
    head = HEADER.pack(SYNC, kind, len(payload))
    return head + payload + CRC.pack(zlib.crc32(head[2:] + payload))


class FrameDecoder:
    """Bytes in, (type, payload) out. ``stats`` counts frames, crc_errors, resyncs, bytes_discarded, oversize."""

    def __init__(self, max_payload: int, kinds: set[int]) -> None:
        self.max_payload = max_payload
        self.kinds = kinds
        self.buffer = bytearray()
        self.stats = {"frames": 0, "crc_errors": 0, "resyncs": 0, "bytes_discarded": 0, "oversize": 0,
                      "unknown_type": 0, "frame_bytes": 0}
        self._in_sync = True

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        buf = self.buffer
        buf += data
        out = []
        while True:
            start = buf.find(SYNC)
            if start < 0:
                keep = 1 if buf.endswith(SYNC[:1]) else 0  # a sync word may be split across reads
                self._discard(len(buf) - keep)
                break
            if start:
                self._discard(start)
            if len(buf) < HEADER.size:
                break
            _, kind, length = HEADER.unpack_from(buf)
            if length > self.max_payload or kind not in self.kinds:
                self.stats["oversize" if length > self.max_payload else "unknown_type"] += 1
                self._discard(1)  # this sync was payload; hunt for the next one
                continue
            end = HEADER.size + length + CRC.size
            if len(buf) < end:
                break
            payload = bytes(buf[HEADER.size:HEADER.size + length])
            (crc,) = CRC.unpack_from(buf, HEADER.size + length)
            if crc != zlib.crc32(bytes(buf[2:HEADER.size]) + payload):
                self.stats["crc_errors"] += 1
                self._discard(1)
                continue
            del buf[:end]
            self._in_sync = True
            self.stats["frames"] += 1
            self.stats["frame_bytes"] += end
            out.append((kind, payload))
        return out

    def _discard(self, n: int) -> None:
        if n <= 0:
            return
        del self.buffer[:n]
        self.stats["bytes_discarded"] += n
        if self._in_sync:
            self.stats["resyncs"] += 1
            self._in_sync = False
