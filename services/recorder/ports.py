"""recorder: records the keys a start command names (default xm/**), so its inputs are not fixed
here; it stores every key the registry (shared/keys.py) types."""

from shared.ports import Ports

PORTS = Ports(service="recorder", doc="MCAP recorder, on command")
