"""How the bridge's frames travel: addresses, ZeroMQ, the plain-socket transport, CURVE."""

from protocol.transport.endpoint import (
    DEFAULT_ADDRESS,
    Endpoint,
    new_routing_id,
    parse_endpoint,
    require_loopback_for_direct,
)

__all__ = [
    "DEFAULT_ADDRESS",
    "Endpoint",
    "new_routing_id",
    "parse_endpoint",
    "require_loopback_for_direct",
]
