"""The shared runtime: typed Zenoh pub/sub bridged into asyncio, health, clock, logging."""

from shared.runtime.clock import Clock
from shared.runtime.node import Node, Publisher, QueuePolicy, Subscription, fifo, latest
from shared.runtime.service import run_node, service_main
from shared.runtime.zsession import EndpointError, check_port_free, open_client, open_router

__all__ = [
    "Clock", "EndpointError", "Node", "Publisher", "QueuePolicy", "Subscription", "check_port_free", "fifo",
    "latest", "open_client", "open_router", "run_node", "service_main",
]
