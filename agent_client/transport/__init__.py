"""The learner's transports: one `Channel` interface, ZeroMQ and direct:// implementations.

`connect` picks the implementation from the address scheme.
"""

from __future__ import annotations

import time

from agent_client.defaults import STEP_TIMEOUT_S
from agent_client.errors import ServerUnavailable
from agent_client.transport.channel import CLIENT_NAME, Channel
from agent_client.transport.direct import DirectChannel
from agent_client.transport.zeromq import ZmqChannel
from protocol.messages import Welcome
from protocol.transport.endpoint import parse_endpoint
from protocol.transport.security import ClientCredentials
from protocol.transport.zeromq import HEARTBEAT_TIMEOUT_MS

__all__ = ["CLIENT_NAME", "Channel", "DirectChannel", "ZmqChannel", "connect", "wait_for_server"]


def connect(
    address: str,
    timeout_s: float = STEP_TIMEOUT_S,
    credentials: ClientCredentials | None = None,
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_MS / 1000,
    spin_us: float | None = None,
    routing_id: bytes | None = None,
) -> Channel:
    """A channel to `address`: ZeroMQ for ``tcp://`` and ``ipc://``, a plain socket for
    ``direct://`` (`spin_us`: how long to busy-wait for a reply; direct only). `routing_id`
    names this client to the server (default: a fresh `new_routing_id()`)."""
    if parse_endpoint(address).scheme == "direct":
        if credentials is not None:
            raise ValueError("direct:// has no CURVE authentication: use tcp:// with keys")
        return DirectChannel(address, timeout_s, spin_us=spin_us, routing_id=routing_id)
    return ZmqChannel(address, timeout_s, credentials, heartbeat_timeout_s, routing_id)


def wait_for_server(address: str, timeout_s: float = 30.0) -> Welcome:
    """Retry hello until the server answers (for scripts that just started one)."""
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        with connect(address, timeout_s=max(0.1, min(1.0, remaining))) as connection:
            try:
                return connection.hello()
            except ServerUnavailable:
                if time.monotonic() >= deadline:
                    raise
