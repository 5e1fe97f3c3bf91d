"""docker/k8s/av-bridge.yaml agrees with the code: images, commands, ports, keys, replicas."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from protocol.transport.security import CLIENT_SECRET_ENV, SERVER_KEY_ENV
from tests.test_docker import default_port, parse_agent_client, parse_sim_server

MANIFEST = Path(__file__).resolve().parents[1] / "docker" / "k8s" / "av-bridge.yaml"
DOCUMENTS = {doc["kind"]: doc for doc in yaml.safe_load_all(MANIFEST.read_text())}


def container(kind: str) -> dict[str, Any]:
    spec = DOCUMENTS[kind]["spec"]["template"]["spec"]
    (only,) = spec["containers"]
    return dict(only)


def test_servers_bind_the_default_port_with_authentication() -> None:
    server = container("StatefulSet")
    args = parse_sim_server(server["args"])
    port = default_port()
    assert args.bind == f"tcp://0.0.0.0:{port}"
    assert str(args.secret_key).startswith("/keys/") and str(args.authorized_keys) == "/keys"
    assert server["ports"][0]["containerPort"] == port
    assert DOCUMENTS["Service"]["spec"]["ports"][0]["port"] == port
    assert DOCUMENTS["Service"]["spec"]["clusterIP"] == "None"  # a DNS name per pod
    assert server["image"] == "av-bridge-server"


def test_the_learner_steps_every_replica_with_keys() -> None:
    learner = container("Job")
    args = parse_agent_client(learner["args"])
    replicas = DOCUMENTS["StatefulSet"]["spec"]["replicas"]
    service = DOCUMENTS["StatefulSet"]["spec"]["serviceName"]
    expected = [f"tcp://server-{i}.{service}:{default_port()}" for i in range(replicas)]
    assert args.command == "train" and args.server == expected
    env = {item["name"]: item["value"] for item in learner["env"]}
    assert set(env) == {SERVER_KEY_ENV, CLIENT_SECRET_ENV}
    assert learner["image"] == "av-bridge-learner"


def test_pods_run_as_the_image_user_and_can_read_the_keys() -> None:
    for kind in ("StatefulSet", "Job"):
        security = DOCUMENTS[kind]["spec"]["template"]["spec"]["securityContext"]
        assert security["runAsUser"] == 10001 and security["fsGroup"] == 10001
