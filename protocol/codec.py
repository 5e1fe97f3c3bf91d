"""The one module that touches msgpack: messages to frames and back, with validation.

Decoding never trusts the peer: it checks the frame size, the msgpack structure, every field's
type and that every number is finite, and raises `ProtocolError` with a distinct `ErrorCode` for
each kind of fault. Map keys the receiver does not know are ignored (forward compatibility within
a major version); missing keys fall back to the field's default or are an error.

Two paths, one verdict:

* **The precise path**, for every message. Writing: the generic dataclass walk (`_wire_map`)
  and msgpack. Reading: msgpack, then a converter compiled once per class from its dataclass
  fields and type hints (as `dataclasses` compiles ``__init__``), which checks each field with
  an inline test of its exact msgpack type and hands anything that fails it to the field's
  converter, which converts (an integer where a float is expected) or raises the field's error.
* **The fast path**, for the fixed-shape messages: those made of scalars, nested messages of
  scalars and arrays of either, which are the ones sent at every step (`Step`, `Observation`;
  also `Close`, `Bye`, `Error`). msgspec packs them, and reads them straight into the
  dataclass, checking structure and types. A compiled check then adds what msgspec does not
  check (finite numbers, int64, string lengths). What each path costs: docs/results.md,
  "Bridge performance".

The fast path accepts a frame only if it is the frame `encode` writes for the message read from
it. The precise path decodes that frame to the same message (the tests check both directions),
so the fast path cannot accept what the precise path would refuse. This also covers what msgspec
reads differently: it skips the values of keys it does not know unread, and it reads the first
of two ``type`` keys. Any other frame, e.g. from another implementation's encoder, takes the
precise path and gets its verdict.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import types
import typing
from collections.abc import Callable
from functools import cache
from typing import Any

import msgpack
import msgspec

from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import REPLY_TYPES, REQUEST_TYPES, Message, MultiObservation, Observation

DEFAULT_MAX_FRAME_BYTES = 64 * 1024
"""Largest frame a peer must accept; servers announce theirs in `Welcome.max_frame_bytes`."""

_MAX_STRING = 4096
_MAX_ITEMS = 1024
_INT64 = 2**63

Converter = Callable[[Any, str], Any]

_REQUESTS = {cls.TYPE: cls for cls in REQUEST_TYPES}
_REPLIES = {cls.TYPE: cls for cls in REPLY_TYPES}


def encode(message: Message) -> bytes:
    """Serialise a message to one msgpack frame (a map whose ``type`` key names the message)."""
    cls: type = type(message)
    if _range_check(cls) is None:  # not of a fixed shape: hello, reset, welcome
        return msgpack.packb(_wire_map(message), use_bin_type=True)
    fields = _ENCODER.encode(message)  # the map of the fields, in declaration order
    entry = _TYPE_ENTRIES[cls]
    for name, tail in _NIL_TAILS.get(cls, ()):  # keys of a later minor version left out when nil
        if getattr(message, name) is not None:
            break
        fields = bytes((fields[0] - 1,)) + fields[1 : -len(tail)]
    head = fields[0]
    if head < 0x8F:  # a fixmap (0x80-0x8e): one more entry fits in the same byte
        return bytes((head + 1,)) + entry + fields[1:]
    if head == 0x8F:
        return b"\xde\x00\x10" + entry + fields[1:]
    assert head == 0xDE, "a message of more than 65534 fields"
    (count,) = _MAP16.unpack_from(fields, 1)
    return b"\xde" + _MAP16.pack(count + 1) + entry + fields[3:]


def _encode_other(value: Any) -> Any:
    """What msgspec does not pack itself: subclasses of float (numpy's float64), int, str."""
    for base in (float, int, str):
        if isinstance(value, base):
            return base(value)
    raise TypeError(f"cannot encode {type(value).__name__} on the wire")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_encode_other)
_MAP16 = struct.Struct(">H")


_NIL_TAILS: dict[type, tuple[tuple[str, bytes], ...]] = {
    Observation: tuple(
        (name, msgpack.packb(name) + b"\xc0") for name in ("route", "road", "traffic", "safety")
    ),
    MultiObservation: ((("traffic", msgpack.packb("traffic") + b"\xc0")),),
}
"""The trailing optional fields (last first) of 1.3, 1.6 and 1.8 that `encode` leaves out when nil,
with their packed ``key: nil`` entries: a 1.2 peer's frame and ours are then the same bytes, and
keep the fast path on both sides. Only for fixmaps (fewer than 15 fields), whose count is in
byte 0."""

_TYPE_ENTRIES = {
    cls: msgpack.packb("type") + msgpack.packb(cls.TYPE) for cls in REQUEST_TYPES + REPLY_TYPES
}
"""The packed ``type`` key and value of each message class: the first entry of its map."""


def decode_request(frame: bytes, max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> Message:
    """Parse a frame sent by a client; raises `ProtocolError` on anything malformed."""
    return _decode(frame, _REQUESTS, max_frame_bytes)


def decode_reply(frame: bytes, max_frame_bytes: int = 1024 * 1024) -> Message:
    """Parse a frame sent by a server; raises `ProtocolError` on anything malformed."""
    return _decode(frame, _REPLIES, max_frame_bytes)


def _decode(frame: bytes, allowed: dict[str, type], max_frame_bytes: int) -> Message:
    if len(frame) > max_frame_bytes:
        raise ProtocolError(
            ErrorCode.FRAME_TOO_LARGE,
            f"frame of {len(frame)} bytes exceeds the limit of {max_frame_bytes} bytes",
        )
    leading = leading_type(frame)
    fast = _fast_decoder(allowed[leading]) if leading in allowed else None
    if fast is not None:
        decoder, in_range = fast
        try:
            message = decoder.decode(frame)
        except (msgspec.MsgspecError, RecursionError):
            pass  # the precise path says what is wrong
        else:
            if in_range(message) and encode(message) == frame:
                return typing.cast(Message, message)
    try:
        raw = msgpack.unpackb(frame, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types on hostile input
        raise ProtocolError(
            ErrorCode.DECODE_ERROR, f"frame is not valid msgpack: {type(exc).__name__}: {exc}"
        ) from exc
    if not isinstance(raw, dict):
        raise ProtocolError(
            ErrorCode.DECODE_ERROR, f"frame must be a msgpack map, got {type(raw).__name__}"
        )
    _check_plain(raw)
    kind = raw.get("type")
    if not isinstance(kind, str):
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "message has no string 'type' key")
    cls = allowed.get(kind)
    if cls is None:
        known = ", ".join(sorted(allowed))
        raise ProtocolError(
            ErrorCode.UNKNOWN_TYPE, f"unknown message type {kind[:64]!r} (expected one of {known})"
        )
    return typing.cast(Message, _converter(cls)(raw, kind))


# --------------------------------------------------------------------------- to the wire


def _wire_map(message: Any) -> dict[str, Any]:
    """The precise path's wire map of a message (generic, slow): the bytes `encode` must write."""
    wire = {"type": message.TYPE}
    wire.update(_to_wire(message))
    for name, _ in _NIL_TAILS.get(type(message), ()):
        if wire[name] is not None:
            break
        del wire[name]
    return wire


def _to_wire(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {name: _to_wire(getattr(value, name)) for name in _field_names(type(value))}
    if isinstance(value, tuple | list):
        return [_to_wire(item) for item in value]
    if isinstance(value, dict):
        return {key: _to_wire(item) for key, item in value.items()}
    if isinstance(value, bool | str) or value is None:
        return value
    if isinstance(value, int):
        return int(value)  # IntEnum -> plain int
    if isinstance(value, float):
        return value
    raise TypeError(f"cannot encode {type(value).__name__} on the wire")


@cache
def _field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


# --------------------------------------------------------------------------- from the wire


_PLAIN = (str, int, float, bool, type(None))


def _check_plain(raw: dict[str, Any]) -> None:
    """Refuse what the protocol never sends: non-string map keys, bin and ext values, anywhere.

    msgpack's strict map keys still let bin keys through, and bin and ext values are read as
    bytes and extension objects; each is a `decode_error`, whether its key is known or not.
    Iterative, as a frame may nest up to msgpack's own limit of 1023 levels.
    """
    stack: list[Any] = [raw]
    while stack:
        value = stack.pop()
        if isinstance(value, dict):
            for key in value:
                if type(key) is not str:
                    raise ProtocolError(
                        ErrorCode.DECODE_ERROR,
                        f"map key of type {_wire_kind(key)}: every map key must be a string",
                    )
            stack.extend(value.values())
        elif isinstance(value, list):
            stack.extend(value)
        elif not isinstance(value, _PLAIN):
            raise ProtocolError(
                ErrorCode.DECODE_ERROR,
                f"value of type {_wire_kind(value)}: the protocol uses nil, booleans, integers, "
                "floats, strings, arrays and maps only",
            )


def _wire_kind(value: Any) -> str:
    """The msgpack family of a decoded value, for error messages."""
    if isinstance(value, bytes):
        return "bin"
    if isinstance(value, msgpack.ExtType | msgpack.Timestamp):
        return "ext"
    return type(value).__name__


def _invalid(path: str, expected: str, value: Any) -> ProtocolError:
    return ProtocolError(
        ErrorCode.INVALID_MESSAGE,
        f"{path}: expected {expected}, got {type(value).__name__}",
        field=path,
    )


def _as_float(value: Any, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _invalid(path, "a number", value)
    number = float(value)
    if not math.isfinite(number):
        raise ProtocolError(
            ErrorCode.INVALID_NUMBER, f"{path}: {number} is not a finite number", field=path
        )
    return number


def _as_int(value: Any, path: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _invalid(path, "an integer", value)
    if not -_INT64 <= value < _INT64:
        raise ProtocolError(
            ErrorCode.INVALID_NUMBER, f"{path}: {value} is out of int64 range", field=path
        )
    return value


def _as_bool(value: Any, path: str) -> bool:
    if not isinstance(value, bool):
        raise _invalid(path, "a boolean", value)
    return value


def _as_str(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise _invalid(path, "a string", value)
    if len(value) > _MAX_STRING:
        raise ProtocolError(
            ErrorCode.INVALID_MESSAGE, f"{path}: string longer than {_MAX_STRING}", field=path
        )
    return value


def _as_none(value: Any, path: str) -> None:
    if value is not None:
        raise _invalid(path, "nil", value)
    return None


def _scalar(value: Any, path: str) -> Any:
    """An option value: nil, boolean, integer, finite float or string."""
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, int):
        return _as_int(value, path)
    if isinstance(value, float):
        return _as_float(value, path)
    if isinstance(value, str):
        return _as_str(value, path)
    raise _invalid(path, "nil, a boolean, a number or a string", value)


_SCALARS: dict[Any, Converter] = {
    float: _as_float,
    int: _as_int,
    bool: _as_bool,
    str: _as_str,
    type(None): _as_none,
}


def _union(options: list[Converter], names: str) -> Converter:
    others = [option for option in options if option is not _as_none]
    if len(others) == 1:  # Optional[X]: let X's own, more precise error through
        only = others[0]

        def optional(value: Any, path: str) -> Any:
            return None if value is None else only(value, path)

        return optional

    def convert(value: Any, path: str) -> Any:
        if value is None and _as_none in options:
            return None
        for option in options:
            if option is _as_none:
                continue
            try:
                return option(value, path)
            except ProtocolError as exc:
                if exc.code is ErrorCode.INVALID_NUMBER:
                    raise
        raise _invalid(path, names, value)

    return convert


def _tuple(item: Converter, length: int | None) -> Converter:
    def convert(value: Any, path: str) -> tuple[Any, ...]:
        if not isinstance(value, list | tuple):
            raise _invalid(path, "an array", value)
        if length is not None and len(value) != length:
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE,
                f"{path}: expected {length} items, got {len(value)}",
                field=path,
            )
        if len(value) > _MAX_ITEMS:
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE, f"{path}: more than {_MAX_ITEMS} items", field=path
            )
        return tuple(item(v, f"{path}[{i}]") for i, v in enumerate(value))

    return convert


def _mapping(item: Converter) -> Converter:
    def convert(value: Any, path: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise _invalid(path, "a map", value)
        if len(value) > _MAX_ITEMS:
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE, f"{path}: more than {_MAX_ITEMS} keys", field=path
            )
        return {_as_str(k, path): item(v, f"{path}.{k}") for k, v in value.items()}

    return convert


def _converter_for(hint: Any) -> Converter:
    if hint in _SCALARS:
        return _SCALARS[hint]
    if dataclasses.is_dataclass(hint):
        return _converter(typing.cast(type, hint))
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        names = " or ".join(getattr(a, "__name__", str(a)) for a in args)
        return _union([_converter_for(a) for a in args], names)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return _tuple(_converter_for(args[0]), None)
        items = [_converter_for(a) for a in args]

        def fixed(value: Any, path: str) -> tuple[Any, ...]:
            values = _tuple(_scalar, len(items))(value, path)
            return tuple(
                conv(v, f"{path}[{i}]")
                for i, (conv, v) in enumerate(zip(items, values, strict=True))
            )

        return fixed
    if origin is dict:
        value_hint = args[1]
        if typing.get_origin(value_hint) in (typing.Union, types.UnionType):
            return _mapping(_scalar)
        return _mapping(_converter_for(value_hint))
    raise TypeError(f"no wire converter for {hint!r}")


def _guard(hint: Any, v: str) -> str | None:
    """A Python expression true when the msgpack value named `v` is already valid for `hint`.

    msgpack hands out exact built-in types, so ``type(v) is float`` is exact. Values that fail
    the guard go to the field's converter, which converts them or raises the precise error.
    """
    if hint is float:
        return f"type({v}) is float and isfinite({v})"
    if hint is int:
        return f"type({v}) is int and {-_INT64} <= {v} < {_INT64}"
    if hint is bool:
        return f"({v} is True or {v} is False)"
    if hint is str:
        return f"type({v}) is str and len({v}) <= {_MAX_STRING}"
    if hint is type(None):
        return f"{v} is None"
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        guards = [_guard(a, v) for a in typing.get_args(hint)]
        if all(guards):
            return " or ".join(f"({g})" for g in guards)
    return None


@cache
def _converter(cls: type) -> Converter:
    """Compile (once per class) a function that turns a wire map into an instance of `cls`.

    Fields are checked in declaration order, so the first fault reported is the same whatever
    path found it; the instance is built positionally.
    """
    hints = typing.get_type_hints(cls)
    env: dict[str, Any] = {
        "cls": cls,
        "isfinite": math.isfinite,
        "_invalid": _invalid,
        "_missing": _missing,
        "_MISSING": _MISSING,
    }
    lines = [
        "def convert(value, path):",
        "    if type(value) is not dict:",
        "        raise _invalid(path, 'a map', value)",
        "    get = value.get",
    ]
    names = []
    for i, f in enumerate(dataclasses.fields(cls)):
        if not f.init or f.kw_only:
            raise TypeError(f"{cls.__name__}.{f.name}: only positional init fields are supported")
        v = f"v{i}"
        names.append(v)
        env[f"c{i}"] = _converter_for(hints[f.name])
        lines.append(f"    {v} = get({f.name!r}, _MISSING)")
        lines.append(f"    if {v} is _MISSING:")
        if f.default is not dataclasses.MISSING:
            env[f"d{i}"] = f.default
            lines.append(f"        {v} = d{i}")
        elif f.default_factory is not dataclasses.MISSING:
            env[f"d{i}"] = f.default_factory
            lines.append(f"        {v} = d{i}()")
        else:
            lines.append(f"        raise _missing(path, {f.name!r})")
        guard = _guard(hints[f.name], v)
        lines.append(f"    elif not ({guard}):" if guard else "    else:")
        lines.append(f"        {v} = c{i}({v}, path + {'.' + f.name!r})")
    setters = _slot_setters(cls)
    if setters is None:
        lines.append(f"    return cls({', '.join(names)})")
    else:  # what the frozen dataclass __init__ does, without its per-field object.__setattr__
        env["new"] = object.__new__
        env.update({f"s{i}": setter for i, setter in enumerate(setters)})
        lines.append("    o = new(cls)")
        lines.extend(f"    s{i}(o, {v})" for i, v in enumerate(names))
        lines.append("    return o")
    exec("\n".join(lines) + "\n", env)  # built above from field names only
    convert: Converter = env["convert"]
    convert.__qualname__ = f"decode_{cls.__name__}"
    return convert


_MISSING = object()


def _slot_setters(cls: type) -> list[Callable[[Any, Any], None]] | None:
    """The slot setters of a ``slots=True`` dataclass whose __init__ only stores its fields.

    Filling the slots directly builds the same instance as calling the class, twice as fast
    for a frozen dataclass; None (call the class) when __init__ may do more than that.
    """
    if hasattr(cls, "__post_init__") or "__slots__" not in vars(cls):
        return None
    setters = []
    for f in dataclasses.fields(cls):
        slot = vars(cls).get(f.name)
        if not isinstance(slot, types.MemberDescriptorType):
            return None
        setters.append(slot.__set__)
    return setters


def _missing(path: str, name: str) -> ProtocolError:
    return ProtocolError(
        ErrorCode.INVALID_MESSAGE, f"{path}: missing field {name!r}", field=f"{path}.{name}"
    )


# --------------------------------------------------------------------------- the fast path


def leading_type(frame: bytes) -> str | None:
    """The message type named by the frame's first key if that key is ``type`` (else None): a
    look at a frame without decoding it (the codec's fast path, a pool's routing)."""
    if not frame:
        return None
    head = frame[0]
    start = 1 if 0x80 <= head <= 0x8F else 3 if head == 0xDE else 0
    if not start or frame[start : start + 5] != b"\xa4type":
        return None
    size = frame[start + 5] - 0xA0 if len(frame) > start + 5 else -1  # a fixstr: 0xa0-0xbf
    if not 0 <= size < 32:
        return None
    return frame[start + 6 : start + 6 + size].decode("utf-8", "replace")


@cache
def _fast_decoder(cls: type) -> tuple[msgspec.msgpack.Decoder[Any], Callable[[Any], bool]] | None:
    """msgspec's decoder of `cls` and the check of what it does not check, or None.

    Only messages made of scalars (possibly optional) and nested messages of the same kind have
    a fast path. msgspec checks the types of the fields it reads, but lets floats be infinite
    or NaN, integers go beyond int64 and strings be of any length: the check is for those.
    """
    check = _range_check(cls)
    return None if check is None else (msgspec.msgpack.Decoder(cls), check)


@cache
def _range_check(cls: type) -> Callable[[Any], bool] | None:
    """Compile (once per class) a test that every number of an instance is finite and every
    integer within int64, and its strings short; None if `cls` has fields of another kind.

    The test is a sufficient condition, cheap to evaluate: the floats are summed (a NaN or an
    infinity makes the sum non-finite) and so are the string lengths. An instance that fails it
    (also one whose finite floats overflow in the sum) takes the precise path.
    """
    hints = typing.get_type_hints(cls)
    env: dict[str, Any] = {"isfinite": math.isfinite}
    floats, lengths, tests = ["0.0"], ["0"], []
    for i, f in enumerate(dataclasses.fields(cls)):
        hint, value = hints[f.name], f"o.{f.name}"
        args = typing.get_args(hint)
        optional = typing.get_origin(hint) in (typing.Union, types.UnionType)
        if optional and (len(args) != 2 or type(None) not in args):
            return None
        kind = next(a for a in args if a is not type(None)) if optional else hint
        if kind in (bool, type(None)):
            continue
        if kind is float:
            floats.append(f"({value} or 0.0)" if optional else value)
        elif kind is str:
            lengths.append(f"len({value} or '')" if optional else f"len({value})")
        elif kind is int:
            number = f"({value} or 0)" if optional else value
            tests.append(f"{-_INT64} <= {number} < {_INT64}")
        elif dataclasses.is_dataclass(kind):
            nested = _range_check(typing.cast(type, kind))
            if nested is None:
                return None
            env[f"k{i}"] = nested
            tests.append(f"((x := {value}) is None or k{i}(x))" if optional else f"k{i}({value})")
        elif not _array_check(kind, f"({value} or ())" if optional else value, i, env, tests):
            return None
    tests += [f"isfinite({' + '.join(floats)})", f"{' + '.join(lengths)} <= {_MAX_STRING}"]
    exec("def in_range(o):\n    return " + " and ".join(tests) + "\n", env)  # field names only
    in_range: Callable[[Any], bool] = env["in_range"]
    in_range.__qualname__ = f"in_range_{cls.__name__}"
    return in_range


def _array_check(hint: Any, items: str, index: int, env: dict[str, Any], tests: list[str]) -> bool:
    """Add to `tests` the range test of a ``tuple[X, ...]`` field (expression `items`): at most
    `_MAX_ITEMS` items, each a finite float, an int64, a short string or a message of scalars;
    False if `hint` is not such an array."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is not tuple or len(args) != 2 or args[1] is not Ellipsis:
        return False
    item = args[0]
    tests.append(f"len({items}) <= {_MAX_ITEMS}")
    if item is float:
        tests.append(f"isfinite(sum({items}))")
    elif item is int:
        tests.append(f"all({-_INT64} <= n < {_INT64} for n in {items})")
    elif item is str:
        tests.append(f"max(map(len, {items}), default=0) <= {_MAX_STRING}")
    elif dataclasses.is_dataclass(item):
        nested = _range_check(typing.cast(type, item))
        if nested is None:
            return False
        env[f"a{index}"] = nested
        tests.append(f"all(map(a{index}, {items}))")
    elif item is not bool:
        return False
    return True
