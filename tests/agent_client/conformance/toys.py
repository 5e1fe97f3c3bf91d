"""Servers for the kit to judge: our real ZeroMQ serving loop and `Session` with the fake
backend, in a thread, and broken variants that each break one rule of docs/protocol.md.

A variant overrides `answer` (the reply frame to one request frame, or None for silence) or
`send` (how a reply goes back: envelope, once or twice), or the session's ownership.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import replace
from typing import Any

import msgpack
import zmq

from protocol.codec import decode_reply, decode_request, encode
from protocol.errors import ProtocolError
from protocol.messages import (
    AppliedAction,
    Bye,
    Command,
    Error,
    Hello,
    Message,
    MultiObservation,
    MultiStep,
    Observation,
    Reset,
    ScenarioInfo,
    Step,
    Welcome,
)
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.fake import FakeBackend
from sim_server.serve.zeromq import Server
from sim_server.session import Session

SILENCE = b"\xc1 silence"
"""What `answer` turned into for the serving loop: send nothing."""


class _Routed(Session):
    """The session behind the loop: every request goes through the toy's `answer`."""

    def __init__(self, toy: ToyServer) -> None:
        super().__init__(FakeBackend())
        self.toy = toy

    def handle(self, peer: bytes, frame: bytes, now: float | None = None) -> bytes:
        reply = self.toy.answer(peer, frame)
        return SILENCE if reply is None else reply

    def owner_disconnected(self) -> None:
        if self.toy.notices_disconnection:
            super().owner_disconnected()


class ToyServer(Server):
    """A conforming server in a thread (our serving loop); subclasses break one rule."""

    notices_disconnection = True
    handover = True

    def __init__(self) -> None:
        super().__init__(_Routed(self), "tcp://127.0.0.1:0")
        if not self.handover:
            self._front.socket.setsockopt(zmq.ROUTER_HANDOVER, 0)
        self.address = str(self.endpoint)
        self._thread = threading.Thread(target=self.serve, daemon=True)

    def handle(self, peer: bytes, frame: bytes) -> bytes:
        """What a conforming server answers."""
        return Session.handle(self.session, peer, frame)

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        """The reply frame, or None to stay silent."""
        return self.handle(peer, frame)

    def _send(self, envelope: list[bytes], reply: bytes) -> None:
        if reply is not SILENCE:
            self.send(envelope, reply)

    def send(self, envelope: list[bytes], reply: bytes) -> None:
        """Send one reply behind its envelope."""
        super()._send(envelope, reply)

    def __enter__(self) -> ToyServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self._thread.join(timeout=5)


def zero_reward(prev: object, obs: object, elapsed: float) -> float:
    """A reward for clients of toy servers, whose tests look at the wire, not at learning."""
    return 0.0


def request_of(frame: bytes) -> Message | None:
    try:
        return decode_request(frame)
    except ProtocolError:
        return None


def rewrite_observation(reply: bytes, **changes: Any) -> bytes:
    obs = decode_reply(reply)
    return encode(replace(obs, **changes)) if isinstance(obs, Observation) else reply


def rewrite_welcome(reply: bytes, **changes: Any) -> bytes:
    welcome = decode_reply(reply)
    return encode(replace(welcome, **changes)) if isinstance(welcome, Welcome) else reply


def rewrite_wire(reply: bytes, kind: str, path: tuple[str | int, ...], value: Any) -> bytes:
    """`reply` with one key set (or removed, for `...`) at `path`, if it is of `kind`."""
    wire = msgpack.unpackb(reply, raw=False)
    if wire["type"] != kind:
        return reply
    place = wire
    for key in path[:-1]:
        place = place[key]
    if value is ...:
        place.pop(path[-1], None)
    else:
        place[path[-1]] = value
    return msgpack.packb(wire, use_bin_type=True)


# --------------------------------------------------------------------------- the transport


class DropsRequestId(ToyServer):
    """Answers [routing id, empty, reply]: the REQ socket's request-id frame is dropped."""

    def send(self, envelope: list[bytes], reply: bytes) -> None:
        super().send([envelope[0], b""], reply)


class AnswersTwice(ToyServer):
    """Sends every reply twice."""

    def send(self, envelope: list[bytes], reply: bytes) -> None:
        super().send(envelope, reply)
        super().send(envelope, reply)


class AnswersLate(ToyServer):
    """Answers step 3 of each episode after `delay_s` (longer than the client waits)."""

    delay_s = 1.5

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if isinstance(request, Step) and request.seq == 3:
            time.sleep(self.delay_s)
        return self.handle(peer, frame)


class AnswersAnotherSeq(ToyServer):
    """Answers step k with the observation of step k - 1 (the reply to another request)."""

    def __init__(self) -> None:
        super().__init__()
        self.previous: bytes | None = None

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        request = request_of(frame)
        if isinstance(request, Step) and request.seq > 1 and self.previous is not None:
            reply, self.previous = self.previous, reply
        elif isinstance(request, Step | Reset):
            self.previous = reply
        return reply


class NoHandover(ToyServer):
    """A ROUTER without ZMQ_ROUTER_HANDOVER: a second connection of a client is ignored."""

    handover = False


class KeepsDeadOwner(ToyServer):
    """Never notices that its owner's connection closed: busy until the session timeout."""

    notices_disconnection = False


# --------------------------------------------------------------------------- the welcome


class IntegerDefault(ToyServer):
    """Announces max_episode_time's default as the integer 300 (a JavaScript encoder)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        return rewrite_wire(reply, "welcome", ("scenarios", 0, "options", "max_episode_time"), 300)


class NoStepLength(ToyServer):
    """Announces no step_length; `protocol` is the version it claims (1.2: required)."""

    protocol = PROTOCOL_VERSION

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = rewrite_wire(
            self.handle(peer, frame), "welcome", ("protocol",), list(self.protocol)
        )
        return rewrite_wire(reply, "welcome", ("scenarios", 0, "step_length"), ...)


class OldNoStepLength(NoStepLength):
    """A 1.1 server without step_length: allowed then; the client assumes one and warns."""

    protocol = (1, 1)


class WrongStepLength(ToyServer):
    """Announces a step of 0.05 s, but each step advances 0.1 s (decision_interval 0.1)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        welcome = decode_reply(reply)
        if not isinstance(welcome, Welcome):
            return reply
        info = replace(welcome.scenarios[0], step_length=0.05)
        info = replace(
            info, options={k: v for k, v in info.options.items() if k != "decision_interval"}
        )
        return rewrite_welcome(reply, scenarios=(info,))


class NoDecisionInterval(ToyServer):
    """A scenario without the decision_interval option (every step is one 0.1 s step):
    conforming; the learner runs on it without sending that option."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if isinstance(request, Reset) and "decision_interval" in request.options:
            return encode_error("invalid_option", "scenario cf has no option 'decision_interval'")
        reply = self.handle(peer, frame)
        welcome = decode_reply(reply)
        if not isinstance(welcome, Welcome):
            return reply
        info = welcome.scenarios[0]
        options = {k: v for k, v in info.options.items() if k != "decision_interval"}
        return rewrite_welcome(
            reply, scenarios=(ScenarioInfo(info.name, info.description, options, info.step_length),)
        )


def encode_error(code: str, message: str) -> bytes:
    return encode(Error(code, message))


class VagueVersionMessage(ToyServer):
    """Refuses another major version with a message that names no version."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        if b"version_mismatch" in reply:
            return encode_error("version_mismatch", "major versions differ")
        return reply


# --------------------------------------------------------------------------- observations


class NaNSpeed(ToyServer):
    """Observations carry a NaN ego speed."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        return rewrite_wire(self.handle(peer, frame), "observation", ("ego", "speed"), math.nan)


class LaneOutOfRange(ToyServer):
    """Puts the ego in lane 7 of a one-lane road."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        return rewrite_wire(self.handle(peer, frame), "observation", ("ego", "lane"), 7)


class AppliedLaneChangeFive(ToyServer):
    """Reports an applied lane change of 5 on every step."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        if isinstance(request_of(frame), Step):
            return rewrite_wire(reply, "observation", ("action", "lane_change"), 5)
        return reply


class WrongSeq(ToyServer):
    """Step replies carry the next seq instead of the step's own."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        request = request_of(frame)
        if isinstance(request, Step):
            return rewrite_observation(reply, seq=request.seq + 1)
        return reply


class BothFlags(ToyServer):
    """The last observation of an episode is both terminated and truncated."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        obs = decode_reply(reply)
        if isinstance(obs, Observation) and obs.truncated:
            return encode(replace(obs, terminated=True))
        return reply


class UnknownReason(ToyServer):
    """Ends episodes with the reason "timeout", which the protocol does not define."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        obs = decode_reply(reply)
        if isinstance(obs, Observation) and obs.reason:
            return encode(replace(obs, reason="timeout"))
        return reply


class ReasonWhileRunning(ToyServer):
    """Step observations of a running episode carry a reason."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        obs = decode_reply(reply)
        if isinstance(obs, Observation) and obs.seq and not obs.reason:
            return encode(replace(obs, reason="collision"))
        return reply


class NoRetryCache(ToyServer):
    """A retried step advances the simulation instead of replaying the cached reply."""

    def __init__(self) -> None:
        super().__init__()
        self.offset = self.last_seq = 0

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if isinstance(request, Hello | Reset):
            self.offset = self.last_seq = 0
        if not isinstance(request, Step):
            return self.handle(peer, frame)
        if request.seq == self.last_seq > 0:
            self.offset += 1
        reply = self.handle(peer, encode(replace(request, seq=request.seq + self.offset)))
        if isinstance(decode_reply(reply), Observation):
            self.last_seq = request.seq
        return rewrite_observation(reply, seq=request.seq)


class UnclippedAcceleration(ToyServer):
    """Reports the requested acceleration as applied, far beyond the announced bounds."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        obs = decode_reply(reply)
        if not isinstance(obs, Observation):
            return reply
        action = replace(obs.action, acceleration=obs.action.requested_acceleration)
        return encode(replace(obs, action=action))


class ActionAtSeqZero(ToyServer):
    """The first observation reports an action (1.2: zeros at seq 0)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        if isinstance(request_of(frame), Reset):
            return rewrite_observation(reply, action=AppliedAction(1.0, 0, 1.0, 0))
        return reply


# --------------------------------------------------------------------------- the state machine


class IgnoresSeed(ToyServer):
    """Every reset runs with seed 0: deterministic, but the seed makes no difference."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if isinstance(request, Reset) and request.seed is not None and 0 <= request.seed < 2**31:
            frame = encode(replace(request, seed=0))
        return self.handle(peer, frame)


class WrongErrorCode(ToyServer):
    """Reports invalid_number as invalid_message."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        error = decode_reply(reply)
        if isinstance(error, Error) and error.code == "invalid_number":
            return encode_error("invalid_message", error.message)
        return reply


class NoVersionCheck(ToyServer):
    """Welcomes any protocol version."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        if isinstance(request_of(frame), Hello):
            frame = encode(Hello(PROTOCOL_VERSION))
        return self.handle(peer, frame)


class SilentOnGarbage(ToyServer):
    """Never answers a frame that is not msgpack."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        try:
            msgpack.unpackb(frame)
        except ValueError:
            return None
        return self.handle(peer, frame)


class SeqZeroIsARetry(ToyServer):
    """Answers a step with seq 0 right after reset with the reset's observation."""

    def __init__(self) -> None:
        super().__init__()
        self.first: bytes | None = None

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        reply = self.handle(peer, frame)
        if isinstance(request, Reset):
            self.first = reply
        if isinstance(request, Step) and request.seq == 0 and self.first is not None:
            return self.first
        return reply


class RefusedResetEndsEpisode(ToyServer):
    """A reset of an unknown scenario ends the running episode."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        if b"unknown_scenario" in reply:
            self.session._episode = None
        return reply


class ClosesForOthers(ToyServer):
    """Answers another client's close with bye (and frees the simulator)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if request is not None and request.TYPE == "close" and peer != self.session.owner:
            self.session.owner = None
            return encode(Bye())
        return self.handle(peer, frame)


class AcceptsBin(ToyServer):
    """Reads a bin value as the string it holds (a lenient decoder)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        try:
            raw = msgpack.unpackb(frame, raw=False)
        except Exception:  # the real handler says what is wrong
            return self.handle(peer, frame)
        if isinstance(raw, dict) and isinstance(raw.get("scenario"), bytes):
            raw["scenario"] = raw["scenario"].decode()
            frame = msgpack.packb(raw, use_bin_type=True)
        return self.handle(peer, frame)


# --------------------------------------------------------------------------- many egos (1.4)


class NoEgos(ToyServer):
    """A 1.4 server whose scenario offers no egos option (one ego only)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        return rewrite_wire(
            self.handle(peer, frame), "welcome", ("scenarios", 0, "options", "egos"), ...
        )


class OneEgoOnly(ToyServer):
    """Offers egos but drives one: egos 2 gets invalid_option, as a one-ego backend answers."""

    def __init__(self) -> None:
        super().__init__()
        self.session.backend.max_egos = 1


class MultiWrongSeq(ToyServer):
    """Answers multi_step 2 with a frame numbered 3."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        request = request_of(frame)
        if isinstance(request, MultiStep) and request.seq == 2:
            return rewrite_wire(reply, "multi_observation", ("seq",), 3)
        return reply


class AcceptsAnyCommands(ToyServer):
    """Steps a multi_step without commands as if every running ego had asked for 0 m/s²."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        episode = self.session._episode
        if isinstance(request, MultiStep) and not request.commands and episode and episode.egos:
            commands = tuple(Command(ego, 0.0) for ego in episode.egos)
            frame = encode(replace(request, commands=commands))
        return self.handle(peer, frame)


class ListsEgosTwice(ToyServer):
    """Lists the first ego of every multi-ego frame twice."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        many = decode_reply(reply)
        if isinstance(many, MultiObservation):
            return encode(replace(many, egos=(many.egos[0], *many.egos)))
        return reply


class OldProtocol(ToyServer):
    """A protocol 1.3 server: its welcome says so (it has no egos option)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = rewrite_wire(self.handle(peer, frame), "welcome", ("protocol",), [1, 3])
        return rewrite_wire(reply, "welcome", ("scenarios", 0, "options", "egos"), ...)


class ManyEgosProtocol(ToyServer):
    """A protocol 1.4 server: many egos, but no ``ego_share`` (it came with 1.5)."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        return rewrite_wire(self.handle(peer, frame), "welcome", ("protocol",), [1, 4])


class SilentOnMultiStep(ToyServer):
    """Never answers a multi_step."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        return None if isinstance(request_of(frame), MultiStep) else self.handle(peer, frame)
