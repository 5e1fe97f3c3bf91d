"""The kit's end of the wire: the client's own `Channel`, with raw frames allowed.

A probe sends typed requests, raw msgpack maps or raw bytes, and returns the reply's bytes with
its decoded value, so a check can compare replies byte for byte. Every receive has the channel's
deadline; a lost or late reply is `NoReply` (and the next request goes out on a fresh
connection under the same routing id, as the ZeroMQ guide's Lazy Pirate does), an undecodable
one `BadReply`.
"""

from __future__ import annotations

from typing import Any

import msgpack

from agent_client.errors import BridgeError, MalformedReply, ServerUnavailable
from agent_client.transport import Channel, connect
from protocol.codec import decode_reply, encode
from protocol.errors import ProtocolError
from protocol.messages import MultiStep, Reply, Request, Reset, Step
from protocol.transport.endpoint import new_routing_id

CLIENT_NAME = "agent_client conformance kit"


class NoReply(BridgeError):
    """A request got no reply within its deadline (or the connection broke meanwhile)."""


class BadReply(BridgeError):
    """A reply that is not a valid message of the protocol."""


class Probe:
    """One request in flight over the transport the address names; every receive has a
    deadline."""

    def __init__(self, address: str, timeout_s: float, name: str = "agent-client-check") -> None:
        self.address = address
        self.timeout_s = timeout_s
        self.channel: Channel = connect(address, timeout_s, routing_id=new_routing_id(name))
        self._discarded = 0
        self.timeouts = 0
        """Requests that got no reply in time (their replies may still come, late)."""

    @property
    def discarded(self) -> int:
        """Replies the client's REQ sockets discarded as answering no request in flight."""
        return self._discarded + getattr(self.channel, "discarded", 0)

    def send(self, frame: bytes, timeout_s: float | None = None) -> bytes:
        """Send one frame and return the one-frame reply; raises NoReply after the deadline."""
        deadline = self.timeout_s if timeout_s is None else timeout_s
        try:
            self.channel.send_raw(frame)
            return self.channel.receive_frame(deadline)
        except ServerUnavailable as exc:
            self.timeouts += 1
            self.channel.drop()  # Lazy Pirate: a fresh connection for the next request
            raise NoReply(str(exc)) from exc
        except MalformedReply as exc:
            raise BadReply(str(exc)) from exc
        except BridgeError as exc:
            raise NoReply(str(exc)) from exc

    def exchange(
        self, request: Request | dict[str, Any] | bytes, timeout_s: float | None = None
    ) -> tuple[bytes, Reply]:
        """Send a message (typed, a raw map, or raw bytes); return the reply's bytes and value."""
        if isinstance(request, bytes):
            frame = request
        elif isinstance(request, dict):
            frame = msgpack.packb(request, use_bin_type=True)
        else:
            frame = encode(request)
        data = self.send(frame, timeout_s)
        try:
            reply = decode_reply(data)
        except ProtocolError as exc:
            raise BadReply(
                f"{describe(request)}: malformed reply ({exc.code.value}): {exc.message}"
            ) from exc
        return data, reply  # type: ignore[return-value]

    def ask(
        self, request: Request | dict[str, Any] | bytes, timeout_s: float | None = None
    ) -> Reply:
        return self.exchange(request, timeout_s)[1]

    def drop(self) -> None:
        """Forget the connection; the next request opens a fresh one with the same routing id.

        This is also how a killed client looks to the server: its connection closes, without
        a ``close``."""
        self.channel.drop()

    def handover(self) -> Channel:
        """Go on over a second connection under the same routing id, opened while the first is
        still up (as after a half-open network); returns the first for the caller to close."""
        old = self.channel
        self._discarded += getattr(old, "discarded", 0)
        self.channel = connect(self.address, self.timeout_s, routing_id=old.routing_id)
        return old

    def close(self) -> None:
        self.channel.close()


def describe(request: Request | dict[str, Any] | bytes) -> str:
    """A short name of a request for failure details."""
    if isinstance(request, bytes):
        return f"{len(request)} raw bytes"
    if isinstance(request, dict):
        return f"{request.get('type')!r} map"
    if isinstance(request, Step | MultiStep):
        return f"{request.TYPE} {request.seq}"
    if isinstance(request, Reset):
        many = {k: v for k, v in request.options.items() if k in ("egos", "ego_share")}
        more = "".join(f", {name} {value}" for name, value in many.items())
        return f"reset {request.scenario!r} (seed {request.seed}{more})"
    return request.TYPE
