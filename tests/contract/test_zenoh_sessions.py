"""The project's Zenoh sessions (shared/runtime/zsession.py) as a restarted publisher's subscribers see them."""

from __future__ import annotations

from pathlib import Path

from shared.runtime import open_client
from tests.conftest import Collector, wait_until


def zenoh_shm_mapped_bytes() -> int:
    total = 0
    for line in Path("/proc/self/maps").read_text().splitlines():
        if line.endswith(".zenoh"):
            start, end = line.split()[0].split("-")
            total += int(end, 16) - int(start, 16)
    return total


def test_restarted_publishers_leave_no_shared_memory_pool_mapped_in_the_subscriber(router):
    """Zenoh's implicit shared-memory pool (16 MB per publishing session, mapped into each subscriber
    and kept there after its publisher died: +16-20 MB RSS per restart) is off; what shared memory
    leaves mapped for plain puts is the handshake's small segment per peer (12 kB), not one per
    restart. Large typed payloads use a pool of their own (shared/runtime/shm.py)."""
    endpoint, session = router
    received = Collector(session, "xm/test/**")
    before = zenoh_shm_mapped_bytes()  # other tests of this process may have mapped pools of their own
    try:
        for restart in range(3):
            pub = open_client(endpoint)
            try:
                def through(pub=pub, seen=restart) -> bool:
                    pub.put("xm/test/big", b"x" * 20_000)
                    return len(received.payloads("xm/test/big")) > seen

                wait_until(through, 10, "a 20 kB message through the router")
            finally:
                pub.close()
        assert zenoh_shm_mapped_bytes() - before < 256 * 1024
    finally:
        received.close()
