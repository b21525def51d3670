"""The project's Zenoh sessions (shared/runtime/zsession.py) as a restarted publisher's subscribers see them."""

from __future__ import annotations

from pathlib import Path

from shared.runtime import open_client
from tests.conftest import Collector, wait_until


def zenoh_shm_mappings() -> list[str]:
    return [line for line in Path("/proc/self/maps").read_text().splitlines() if line.endswith(".zenoh")]


def test_restarted_publishers_leave_no_shared_memory_pool_mapped_in_the_subscriber(router):
    """Zenoh's shared-memory transport maps a 16 MB pool of every publishing session into each
    subscriber, and kept a dead publisher's mapped: +16-20 MB RSS per restart. It is off."""
    endpoint, session = router
    received = Collector(session, "xm/test/**")
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
        assert zenoh_shm_mappings() == []
    finally:
        received.close()
