"""Echo servers for the transport floor in `bridge.py`: the cheapest reply Python can give.

    python benchmarks/echo.py zmq tcp://127.0.0.1:0   # a ZeroMQ ROUTER, as sim-server binds
    python benchmarks/echo.py tcp 127.0.0.1:0          # a plain blocking TCP socket

Each answers every request with a fixed reply of ``--reply-bytes`` (an observation's size),
prints ``listening on ADDRESS`` when ready and serves until SIGTERM or the client leaves (tcp).
Length-prefixed frames (4 bytes, little endian) on the plain socket.
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import struct
import sys

import zmq

_LENGTH = struct.Struct("<I")


def serve_zmq(bind: str, reply: bytes) -> None:
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    router.bind(bind.replace(":0", ":*") if bind.endswith(":0") else bind)
    print(f"listening on {router.getsockopt_string(zmq.LAST_ENDPOINT)}", flush=True)
    while True:
        parts = router.recv_multipart()
        router.send_multipart([*parts[:-1], reply])


def serve_tcp(bind: str, reply: bytes) -> None:
    host, _, port = bind.rpartition(":")
    listener = socket.create_server((host, int(port)))
    print(f"listening on {host}:{listener.getsockname()[1]}", flush=True)
    connection, _ = listener.accept()
    connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    framed = _LENGTH.pack(len(reply)) + reply
    while True:
        header = connection.recv(4, socket.MSG_WAITALL)
        if len(header) < 4:
            return
        (size,) = _LENGTH.unpack(header)
        connection.recv(size, socket.MSG_WAITALL)
        connection.sendall(framed)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("zmq", "tcp"))
    parser.add_argument("bind")
    parser.add_argument("--reply-bytes", type=int, default=905)
    args = parser.parse_args()
    reply = b"\x00" * args.reply_bytes
    with contextlib.suppress(KeyboardInterrupt):
        (serve_zmq if args.kind == "zmq" else serve_tcp)(args.bind, reply)
    return 0


if __name__ == "__main__":
    sys.exit(main())
