"""Authentication and encryption of the bridge with ZeroMQ's CURVE (pyzmq's ``zmq.auth``).

One key pair for the server, one for the learners. The server knows its secret key and a
directory of authorised client public keys; a client knows its own key pair and the server's
public key. A client whose public key is not in that directory is refused during the ZeroMQ
handshake: it never reaches the protocol, so it cannot run a step. Key files are ZeroMQ's text
certificates (``*.key`` public, ``*.key_secret`` secret), parsed as text, never executed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

SERVER_KEY_ENV = "AV_BRIDGE_SERVER_KEY"
"""Client side: path of the server's public key file."""
CLIENT_SECRET_ENV = "AV_BRIDGE_SECRET_KEY"
"""Client side: path of the client's secret key file."""


@dataclass(frozen=True)
class KeyPair:
    """A CURVE key pair (Z85-encoded bytes)."""

    public: bytes
    secret: bytes


@dataclass(frozen=True)
class ServerCredentials:
    """What a server needs: its key pair and the directory of authorised client keys."""

    keys: KeyPair
    authorized_keys: Path


@dataclass(frozen=True)
class ClientCredentials:
    """What a client needs: its own key pair and the server's public key."""

    keys: KeyPair
    server_public: bytes

    @classmethod
    def from_files(cls, server_key: Path, secret_key: Path) -> ClientCredentials:
        return cls(load_key_pair(secret_key), load_public_key(server_key))

    @classmethod
    def from_environment(cls) -> ClientCredentials | None:
        """From $AV_BRIDGE_SERVER_KEY and $AV_BRIDGE_SECRET_KEY; None when neither is set."""
        server_key, secret_key = os.environ.get(SERVER_KEY_ENV), os.environ.get(CLIENT_SECRET_ENV)
        if not server_key and not secret_key:
            return None
        if not server_key or not secret_key:
            raise ValueError(f"set both {SERVER_KEY_ENV} and {CLIENT_SECRET_ENV}, or neither")
        return cls.from_files(Path(server_key), Path(secret_key))


def generate_keys(directory: Path) -> list[Path]:
    """Write a server and a client key pair into `directory`; returns the files written.

    Refuses to overwrite existing keys (a lost server key locks every learner out).
    """
    directory.mkdir(parents=True, exist_ok=True)
    names = ("server.key", "server.key_secret", "client.key", "client.key_secret")
    existing = [name for name in names if (directory / name).exists()]
    if existing:
        raise FileExistsError(f"{directory} already holds {', '.join(existing)}; not overwriting")
    for name in ("server", "client"):
        _, secret = zmq.auth.create_certificates(str(directory), name)
        os.chmod(secret, 0o600)
    return [directory / name for name in names]


def load_key_pair(path: Path) -> KeyPair:
    """The key pair of a ``*.key_secret`` file; a clear error for a public key or a bad file."""
    public, secret = _load(path)
    if secret is None:
        raise ValueError(f"{path} holds only a public key: pass the .key_secret file")
    return KeyPair(public, secret)


def load_public_key(path: Path) -> bytes:
    """The public key of a ``*.key`` (or ``*.key_secret``) file."""
    return _load(path)[0]


def _load(path: Path) -> tuple[bytes, bytes | None]:
    if not path.is_file():
        raise ValueError(f"key file {path} does not exist (make keys with `sim-server keygen`)")
    try:
        public, secret = zmq.auth.load_certificate(str(path))
    except (ValueError, OSError, zmq.ZMQError) as exc:
        raise ValueError(f"{path} is not a ZeroMQ CURVE certificate: {exc}") from exc
    if public is None or len(public) != 40:
        raise ValueError(f"{path} holds no valid public key")
    return public, secret


def secure_server_socket(socket: zmq.Socket[bytes], credentials: ServerCredentials) -> None:
    """Make `socket` a CURVE server (call before bind)."""
    socket.curve_secretkey = credentials.keys.secret
    socket.curve_publickey = credentials.keys.public
    socket.curve_server = True


def secure_client_socket(socket: zmq.Socket[bytes], credentials: ClientCredentials) -> None:
    """Make `socket` a CURVE client of the server with that public key (call before connect)."""
    socket.curve_secretkey = credentials.keys.secret
    socket.curve_publickey = credentials.keys.public
    socket.curve_serverkey = credentials.server_public


def start_authenticator(
    context: zmq.Context[zmq.Socket[bytes]], credentials: ServerCredentials
) -> ThreadAuthenticator:
    """Start the ZAP handler that admits only the public keys in `authorized_keys`."""
    if not credentials.authorized_keys.is_dir():
        raise ValueError(f"authorised keys: {credentials.authorized_keys} is not a directory")
    if not any(credentials.authorized_keys.glob("*.key")):
        raise ValueError(f"authorised keys: {credentials.authorized_keys} holds no *.key file")
    authenticator = ThreadAuthenticator(context, log=None)
    authenticator.start()
    authenticator.configure_curve(domain="*", location=str(credentials.authorized_keys))
    return authenticator
