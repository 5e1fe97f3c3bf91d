"""Addresses both peers agree on: the three schemes, the loopback rule, client routing ids.

``tcp://HOST:PORT`` and ``ipc://PATH`` are ZeroMQ (`protocol.transport.zeromq`);
``direct://HOST:PORT`` is the plain-socket transport (`protocol.transport.direct`), which has no
authentication and is therefore bound and reached on loopback addresses only.
"""

from __future__ import annotations

import ipaddress
import os
import secrets
from dataclasses import dataclass

DEFAULT_ADDRESS = "tcp://127.0.0.1:5555"
SCHEMES = ("tcp", "ipc", "direct")


@dataclass(frozen=True)
class Endpoint:
    """A parsed ``tcp://HOST:PORT``, ``ipc://PATH`` or ``direct://HOST:PORT`` address."""

    scheme: str
    host: str = ""
    port: int = 0
    path: str = ""

    def __str__(self) -> str:
        if self.scheme == "ipc":
            return f"ipc://{self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    @property
    def is_loopback(self) -> bool:
        """True for ipc and for tcp/direct on a loopback address or ``localhost``."""
        if self.scheme == "ipc" or self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    @property
    def is_ipv6(self) -> bool:
        return ":" in self.host


def parse_endpoint(address: str) -> Endpoint:
    """Parse and check an address; raises ValueError with the expected forms."""
    if address.startswith("ipc://"):
        path = address[len("ipc://") :]
        if not path:
            raise ValueError(f"{address!r}: ipc address needs a path, e.g. ipc:///tmp/bridge.sock")
        return Endpoint("ipc", path=path)
    scheme, sep, rest = address.partition("://")
    if sep and scheme in ("tcp", "direct"):
        host, sep, port_text = rest.rpartition(":")
        host = host.strip("[]")
        if not sep or not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
            raise ValueError(f"{address!r}: expected {scheme}://HOST:PORT with PORT in 0..65535")
        return Endpoint(scheme, host=host, port=int(port_text))
    raise ValueError(f"{address!r}: expected tcp://HOST:PORT, ipc://PATH or direct://HOST:PORT")


def require_loopback_for_direct(endpoint: Endpoint) -> None:
    """direct:// carries no authentication: refuse it on an address other machines can reach."""
    if endpoint.scheme == "direct" and not endpoint.is_loopback:
        raise ValueError(
            f"{endpoint}: direct:// is unencrypted and for one machine only (a loopback address);"
            " use tcp:// with CURVE keys across machines"
        )


def new_routing_id(role: str = "agent-client") -> bytes:
    """A client's identity for the server, kept across reconnects: role, pid and 32 random bits.

    The server owns its simulation per routing id, so a client that comes back on a fresh socket
    (ZeroMQ) or connection (direct://) with the same id may retry its last step.
    """
    return f"{role}-{os.getpid()}-{secrets.token_hex(4)}".encode()
