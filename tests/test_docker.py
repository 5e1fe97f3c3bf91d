"""The container files (docker/) against the code: fast, no container engine needed.

The images themselves are built and run by ``scripts/containers.sh`` (podman, minutes). Here:
entry points, ports, flags, environment variables and installed extras of the Dockerfiles and of
docker/compose.yaml must agree with pyproject.toml, the argparse parsers and the imports of
each side. compose.yaml is read with a small parser of the YAML subset it uses (block mappings
and lists, JSON-style flow lists), cross-checked with PyYAML when that is installed.
"""

from __future__ import annotations

import ast
import importlib.metadata
import json
import os
import re
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from packaging.requirements import Requirement

from tests.test_dependency_rule import imported_modules

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
LOCAL_PACKAGES = {"protocol", "sim_server", "agent_client"}

IMAGES = ("learner", "server")
DOCKERFILES = {"server": "server.Dockerfile", "learner": "learner.Dockerfile"}
# The project packages each image carries.
SIDES = {"server": {"protocol", "sim_server"}, "learner": {"protocol", "agent_client"}}
# Extras an image leaves out on purpose (installable with --build-arg EXTRAS=...): the modules
# that need them do not work in the image. `highway` is a second simulator backend.
# Extras an image leaves out on purpose (a build argument adds them: docs/docker.md, docs/ray.md).
OMITTED_EXTRAS = {"server": {"highway"}, "learner": {"sb3", "ray", "rllib", "pettingzoo"}}
# Distributions that must never be in an image (the other side's heavy dependencies).
FORBIDDEN_DISTRIBUTIONS = {
    "server": {"torch", "gymnasium", "tensorboard"},
    "learner": {"libsumo", "eclipse-sumo", "sumo-data", "traci", "sumolib"},
}


# ---- a Dockerfile reader --------------------------------------------------------------------


@dataclass
class Stage:
    base: str
    name: str | None
    instructions: list[tuple[str, str]] = field(default_factory=list)

    def all(self, keyword: str) -> list[str]:
        return [args for kw, args in self.instructions if kw == keyword]

    def last(self, keyword: str) -> str:
        found = self.all(keyword)
        assert found, f"no {keyword} in stage FROM {self.base}"
        return found[-1]


@dataclass
class Dockerfile:
    args: dict[str, str]  # ARG defaults before the first FROM
    stages: list[Stage]

    @property
    def final(self) -> Stage:
        return self.stages[-1]


def parse_dockerfile(path: Path) -> Dockerfile:
    """Instructions with continuation lines joined and comments dropped; stages split on FROM."""
    logical: list[str] = []
    pending = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if pending and line.startswith("#"):
            continue  # a comment inside a continued instruction
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        logical.append(pending + line)
        pending = ""
    assert not pending, f"{path.name}: the last instruction ends with a backslash"

    args: dict[str, str] = {}
    stages: list[Stage] = []
    for line in logical:
        keyword, _, rest = line.partition(" ")
        keyword, rest = keyword.upper(), rest.strip()
        if keyword == "FROM":
            words = rest.split()
            name = words[2] if len(words) == 3 and words[1].upper() == "AS" else None
            stages.append(Stage(words[0], name))
        elif not stages:
            assert keyword == "ARG", f"{path.name}: only ARG may precede FROM, found {keyword}"
            key, _, default = rest.partition("=")
            args[key] = default.strip('"')
        else:
            stages[-1].instructions.append((keyword, rest))
    return Dockerfile(args, stages)


def exec_form(text: str) -> list[str]:
    """ENTRYPOINT/CMD must be in exec (JSON) form: signals reach the program, not a shell."""
    value = json.loads(text)
    assert isinstance(value, list), text
    assert all(isinstance(item, str) for item in value), text
    return value


def arg_default(stage: Stage, name: str) -> str:
    for args in stage.all("ARG"):
        key, _, default = args.partition("=")
        if key == name:
            return default.strip('"')
    raise AssertionError(f"no ARG {name}")


def installed_extras(image: str) -> set[str]:
    """The extras of the `pip install "/src[...]"` line of the build stage."""
    stage = dockerfile(image).stages[0]
    installs = [run for run in stage.all("RUN") if "pip install" in run]
    assert len(installs) == 1, installs
    match = re.search(r'"/src\[([^\]]+)\]"', installs[0])
    assert match, f'no "/src[EXTRAS]" in {installs[0]}'
    spec = match.group(1)
    if spec.startswith("${") and spec.endswith("}"):
        spec = arg_default(stage, spec[2:-1])
    return {extra.strip() for extra in spec.split(",")}


def copied_packages(image: str) -> set[str]:
    """Top-level project packages copied into the build context of an image."""
    copies = " ".join(dockerfile(image).stages[0].all("COPY")).split()
    return {word for word in copies if word in LOCAL_PACKAGES}


def dockerfile(image: str) -> Dockerfile:
    return parse_dockerfile(DOCKER / DOCKERFILES[image])


# ---- a reader for the YAML subset of compose.yaml --------------------------------------------


def _strip_comment(line: str) -> str:
    quote = ""
    for index, char in enumerate(line):
        if quote:
            if char == quote:
                quote = ""
        elif char in "\"'":
            quote = char
        elif char == "#" and (index == 0 or line[index - 1] in " \t"):
            return line[:index]
    return line


def _scalar(text: str) -> Any:
    if text.startswith(("[", "{", '"')):
        return json.loads(text)
    if re.fullmatch(r"-?\d+", text):
        return int(text)
    if text in ("true", "false"):
        return text == "true"
    assert not text.startswith(("'", "&", "*", "|", ">", "!")), f"unsupported YAML: {text}"
    return text


def _block(lines: list[tuple[int, str]], index: int, indent: int) -> tuple[Any, int]:
    if lines[index][1].startswith("- "):
        items = []
        while index < len(lines) and lines[index][0] == indent:
            assert lines[index][1].startswith("- "), f"mixed list and mapping: {lines[index]}"
            items.append(_scalar(lines[index][1][2:].strip()))
            index += 1
        value: Any = items
    else:
        mapping: dict[str, Any] = {}
        while index < len(lines) and lines[index][0] == indent:
            key, sep, rest = lines[index][1].partition(":")
            assert sep and key and " " not in key, f"expected KEY: VALUE, got {lines[index]}"
            assert key not in mapping, f"duplicate key {key}"
            rest = rest.strip()
            index += 1
            if rest:
                mapping[key] = _scalar(rest)
            elif index < len(lines) and lines[index][0] > indent:
                mapping[key], index = _block(lines, index, lines[index][0])
            else:
                mapping[key] = None
        value = mapping
    if index < len(lines):
        assert lines[index][0] < indent, f"unexpected indentation: {lines[index]}"
    return value, index


def parse_yaml_subset(text: str) -> Any:
    """Block mappings and lists, scalars, JSON flow lists/maps and double-quoted strings."""
    lines = []
    for raw in text.splitlines():
        assert "\t" not in raw, "tabs in YAML"
        line = _strip_comment(raw).rstrip()
        if line.strip():
            lines.append((len(line) - len(line.lstrip(" ")), line.strip()))
    value, index = _block(lines, 0, lines[0][0])
    assert index == len(lines)
    return value


COMPOSE_TEXT = (DOCKER / "compose.yaml").read_text()
COMPOSE = parse_yaml_subset(COMPOSE_TEXT)
SERVICES: dict[str, dict[str, Any]] = COMPOSE["services"]


def service_image(name: str) -> str:
    """Which of our images a compose service runs."""
    image = SERVICES[name]["image"]
    for key in IMAGES:
        if image == f"av-bridge-{key}":
            return key
    raise AssertionError(f"service {name} runs an unknown image {image}")


# ---- the code's side --------------------------------------------------------------------------


def default_port() -> int:
    from protocol.transport.endpoint import DEFAULT_ADDRESS

    return int(DEFAULT_ADDRESS.rsplit(":", 1)[1])


def parse_sim_server(argv: list[str]) -> Any:
    """Parse a sim-server command line as the real CLI would (keygen has its own parser)."""
    from sim_server import cli

    if argv[:1] == ["keygen"]:
        return cli.build_keygen_parser().parse_args(argv[1:])
    return cli.build_parser().parse_args(argv)


def parse_agent_client(argv: list[str]) -> Any:
    from agent_client.cli.main import build_parser

    return build_parser().parse_args(argv)


PARSERS = {"sim-server": parse_sim_server, "agent-client": parse_agent_client}


def string_constants(packages: set[str]) -> set[str]:
    found: set[str] = set()
    for package in packages:
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Constant) and isinstance(node.value, str):
                    found.add(node.value)
    return found


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement_closure(requirements: list[str]) -> set[str]:
    """Installed distributions reachable from `requirements` (environment markers honoured)."""
    seen: set[str] = set()
    todo = [(Requirement(text), "") for text in requirements]
    while todo:
        requirement, extra = todo.pop()
        if requirement.marker is not None and not requirement.marker.evaluate({"extra": extra}):
            continue
        name = normalise(requirement.name)
        wanted = {f"{name}[{e}]" for e in requirement.extras} | {name}
        if wanted <= seen:
            continue
        seen |= wanted
        try:
            requires = importlib.metadata.requires(name) or []
        except importlib.metadata.PackageNotFoundError:
            continue  # not installed here: its own dependencies are unknown, itself counts
        for text in requires:
            for chosen in ("", *requirement.extras):
                todo.append((Requirement(text), chosen))
    return {item for item in seen if "[" not in item}


def image_distributions(extras: set[str]) -> set[str]:
    optional = PYPROJECT["project"]["optional-dependencies"]
    requirements = list(PYPROJECT["project"]["dependencies"])
    for extra in extras:
        requirements += optional[extra]
    return requirement_closure(requirements)


def third_party_imports(packages: set[str]) -> dict[str, set[str]]:
    """Top-level third-party modules imported by `packages`, with the files importing them."""
    found: dict[str, set[str]] = {}
    for package in packages:
        for path in (ROOT / package).rglob("*.py"):
            for module in imported_modules(path):
                if module in LOCAL_PACKAGES or module in sys.stdlib_module_names:
                    continue
                if module == "__future__":
                    continue
                found.setdefault(module, set()).add(str(path.relative_to(ROOT)))
    return found


# ---- the images -------------------------------------------------------------------------------


@pytest.mark.parametrize("image", IMAGES)
def test_base_image_is_an_argument_defaulting_to_python_slim(image: str) -> None:
    parsed = dockerfile(image)
    assert parsed.args.get("BASE") == "python:3.11-slim"
    assert all(stage.base == "${BASE}" for stage in parsed.stages)
    assert len(parsed.stages) >= 2, "build in one stage, copy the environment into the next"


@pytest.mark.parametrize(
    ("image", "program"), [("server", "sim-server"), ("learner", "agent-client")]
)
def test_entry_point_is_the_project_script(image: str, program: str) -> None:
    assert program in PYPROJECT["project"]["scripts"]
    assert exec_form(dockerfile(image).final.last("ENTRYPOINT")) == [program]


@pytest.mark.parametrize("image", IMAGES)
def test_images_run_as_the_same_unprivileged_user(image: str) -> None:
    final = dockerfile(image).final
    assert final.last("USER") not in ("root", "0")
    # compose.yaml shares one keys volume, whose secret files only their owner may read.
    assert any("--uid 10001" in run for run in final.all("RUN")), "useradd --uid 10001"


def test_server_image_exposes_and_binds_the_default_port() -> None:
    final = dockerfile("server").final
    assert final.last("EXPOSE") == str(default_port())
    args = parse_sim_server(exec_form(final.last("CMD")))
    assert args.bind == f"tcp://0.0.0.0:{default_port()}"


def test_server_image_prebuilds_the_scenarios() -> None:
    runs = dockerfile("server").final.all("RUN")
    assert any("prebuild_scenarios.py" in run for run in runs)


def test_prebuild_script_builds_every_builtin_scenario(tmp_path: Path) -> None:
    from sim_server.backends.sumo.scenarios import BUILTIN_SCENARIOS, find_netconvert

    try:
        find_netconvert()
    except FileNotFoundError:
        pytest.skip("netconvert (eclipse-sumo) not installed")
    result = subprocess.run(
        [sys.executable, str(DOCKER / "prebuild_scenarios.py"), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    built = {path.parent.name.rsplit("-", 1)[0] for path in tmp_path.glob("*/*.sumocfg")}
    assert built == set(BUILTIN_SCENARIOS)


@pytest.mark.parametrize("image", IMAGES)
def test_image_copies_only_its_side(image: str) -> None:
    assert copied_packages(image) == SIDES[image]


@pytest.mark.parametrize("image", IMAGES)
def test_image_extras_provide_every_import_of_its_side(image: str) -> None:
    extras = installed_extras(image)
    optional = PYPROJECT["project"]["optional-dependencies"]
    assert extras <= set(optional), extras
    provided = image_distributions(extras)
    omitted = image_distributions(extras | OMITTED_EXTRAS[image]) - provided
    owners = importlib.metadata.packages_distributions()
    missing = {}
    for module, files in third_party_imports(SIDES[image]).items():
        dists = {normalise(d) for d in owners.get(module, [])}
        assert dists, f"{module} (imported by {sorted(files)}) is not installed in this venv"
        if not dists & provided and not dists & omitted:
            missing[module] = sorted(files)
    assert not missing, f"the {image} image does not install what these modules import: {missing}"


@pytest.mark.parametrize("image", IMAGES)
def test_image_installs_nothing_of_the_other_side(image: str) -> None:
    provided = image_distributions(installed_extras(image))
    assert not provided & FORBIDDEN_DISTRIBUTIONS[image]


def test_learner_image_takes_torch_from_the_cpu_index_by_default() -> None:
    build = dockerfile("learner").stages[0]
    assert "download.pytorch.org/whl/cpu" in arg_default(build, "PIP_EXTRA_ARGS")
    assert any("${PIP_EXTRA_ARGS}" in run for run in build.all("RUN"))


def test_learner_image_installs_resolve_servers() -> None:
    copies = dockerfile("learner").final.all("COPY")
    assert any(
        "docker/resolve-servers.sh" in c and c.endswith("/usr/local/bin/resolve-servers")
        for c in copies
    ), copies


def test_learner_image_ships_the_configs_in_its_working_directory() -> None:
    final = dockerfile("learner").final
    workdir = final.last("WORKDIR")
    copy = ("COPY", f"configs {workdir}/configs")  # --config configs/cf.toml works there
    assert copy in final.instructions
    assert (ROOT / "configs" / "cf.toml").is_file()
    # after the user and its home exist: a COPY first would create the home as root's
    useradd = next(i for i, (kw, args) in enumerate(final.instructions) if "useradd" in args)
    assert final.instructions.index(copy) > useradd


@pytest.mark.parametrize("image", IMAGES)
def test_copied_files_exist(image: str) -> None:
    for stage in dockerfile(image).stages:
        for copy in stage.all("COPY"):
            words = [w for w in copy.split() if not w.startswith("--")]
            if any(w.startswith("--from") for w in copy.split()):
                continue
            for source in words[:-1]:
                assert (ROOT / source).exists(), f"COPY {source}: no such file"


# ---- compose.yaml -----------------------------------------------------------------------------


def test_compose_parser_agrees_with_pyyaml() -> None:
    yaml = pytest.importorskip("yaml")
    assert yaml.safe_load(COMPOSE_TEXT) == COMPOSE


def test_compose_has_keygen_servers_and_a_learner() -> None:
    assert set(SERVICES) == {"keygen", "server", "learner"}
    assert service_image("keygen") == service_image("server") == "server"
    assert service_image("learner") == "learner"
    for name in ("server", "learner"):
        build = SERVICES[name]["build"]
        assert (DOCKER / build["context"]).resolve() == ROOT
        assert (ROOT / build["dockerfile"]).resolve() == DOCKER / DOCKERFILES[name]
    assert SERVICES["keygen"]["profiles"] == ["setup"], "keygen runs only when asked for"


def test_compose_network_is_private_and_shared() -> None:
    networks = COMPOSE["networks"]
    assert len(networks) == 1
    ((network, settings),) = networks.items()
    assert settings["internal"] is True
    assert SERVICES["server"]["networks"] == SERVICES["learner"]["networks"] == [network]
    assert SERVICES["keygen"]["network_mode"] == "none"


def test_compose_servers_bind_their_container_address_with_authentication() -> None:
    from protocol.transport.endpoint import parse_endpoint

    args = parse_sim_server(SERVICES["server"]["command"])
    endpoint = parse_endpoint(args.bind)
    assert not endpoint.is_loopback, "a loopback bind is unreachable from the learner container"
    assert endpoint.port == default_port()
    assert not args.insecure
    assert str(args.secret_key) == "/keys/server.key_secret"
    assert str(args.authorized_keys) == "/keys"


def test_compose_healthcheck_probes_the_server_port() -> None:
    test = SERVICES["server"]["healthcheck"]["test"]
    assert test[0] == "CMD"
    assert f"'127.0.0.1', {default_port()}" in test[-1]


def test_compose_keygen_writes_the_files_the_others_read() -> None:
    args = parse_sim_server(SERVICES["keygen"]["command"])
    keys_volume = [v for v in SERVICES["keygen"]["volumes"] if v.endswith(f":{args.out}")]
    assert len(keys_volume) == 1, "keygen writes into a mounted volume"
    volume = keys_volume[0].split(":")[0]
    assert volume in COMPOSE["volumes"]
    assert f"{volume}:/keys:ro" in SERVICES["server"]["volumes"]
    assert f"{volume}:/keys:ro" in SERVICES["learner"]["volumes"]
    env = SERVICES["learner"]["environment"]
    files = {"server.key", "server.key_secret", "client.key", "client.key_secret"}
    for path in (env["AV_BRIDGE_SERVER_KEY"], env["AV_BRIDGE_SECRET_KEY"]):
        assert Path(path).parent == Path(str(args.out))
        assert Path(path).name in files
    assert Path(env["AV_BRIDGE_SERVER_KEY"]).name == "server.key"
    assert Path(env["AV_BRIDGE_SECRET_KEY"]).name == "client.key_secret"


def test_compose_learner_waits_for_healthy_servers() -> None:
    assert SERVICES["learner"]["depends_on"]["server"]["condition"] == "service_healthy"


def learner_argv(addresses: list[str]) -> list[str]:
    """The agent-client command line resolve-servers builds from compose's learner service."""
    entrypoint = SERVICES["learner"]["entrypoint"]
    assert entrypoint[0] == "resolve-servers"
    target, program = entrypoint[1], entrypoint[2]
    assert program in PYPROJECT["project"]["scripts"]
    port = target.rsplit(":", 1)[1]
    command = SERVICES["learner"]["command"]
    servers = [word for address in addresses for word in ("--server", f"tcp://{address}:{port}")]
    return [command[0], *servers, *command[1:]]


def test_compose_learner_command_parses() -> None:
    entrypoint = SERVICES["learner"]["entrypoint"]
    assert entrypoint[1] == f"server:{default_port()}", "the service name and port of the servers"
    args = parse_agent_client(learner_argv(["10.0.0.2"]))
    assert args.command == "train"


def test_train_takes_every_resolved_server() -> None:
    args = parse_agent_client(learner_argv(["10.0.0.2", "10.0.0.3"]))
    assert list(args.server) == ["tcp://10.0.0.2:5555", "tcp://10.0.0.3:5555"]


@pytest.mark.parametrize("service", ["keygen", "server", "learner"])
def test_compose_environment_is_read_by_the_image(service: str) -> None:
    env = SERVICES[service].get("environment") or {}
    known = string_constants(SIDES[service_image(service)])
    for name in env:
        assert name in known, (
            f"{service}: nothing in the {service_image(service)} image reads {name}"
        )


# ---- resolve-servers.sh -----------------------------------------------------------------------


def run_resolve_servers(
    tmp_path: Path, answers: list[str], *argv: str, **env: str
) -> subprocess.CompletedProcess[str]:
    """Run the script with a fake `getent` answering `answers` (IPv4 addresses)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    lines = "".join(f"{a}       STREAM name\n{a}       DGRAM\n" for a in answers)
    getent = bin_dir / "getent"
    getent.write_text(f"#!/bin/sh\nprintf '%s' {shlex.quote(lines)}\n")
    getent.chmod(0o755)
    environment = {"PATH": f"{bin_dir}:{os.environ.get('PATH', '/usr/bin:/bin')}", **env}
    return subprocess.run(
        ["sh", str(DOCKER / "resolve-servers.sh"), *argv],
        capture_output=True,
        text=True,
        timeout=30,
        env=environment,
        check=False,
    )


def test_resolve_servers_passes_every_replica_to_train(tmp_path: Path) -> None:
    answers = ["10.89.0.12", "10.89.0.3", "10.89.0.3"]
    result = run_resolve_servers(tmp_path, answers, "server:5555", "echo", "train", "--quiet")
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == [
        "train",
        "--server",
        "tcp://10.89.0.3:5555",
        "--server",
        "tcp://10.89.0.12:5555",
        "--quiet",
    ]


def test_resolve_servers_gives_other_subcommands_one_server(tmp_path: Path) -> None:
    answers = ["10.89.0.7", "10.89.0.5"]
    result = run_resolve_servers(tmp_path, answers, "server:5555", "echo", "drive", "--json")
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["drive", "--server", "tcp://10.89.0.5:5555", "--json"]


def test_resolve_servers_gives_up_after_its_timeout(tmp_path: Path) -> None:
    result = run_resolve_servers(tmp_path, [], "server:5555", "echo", "train", RESOLVE_TIMEOUT="0")
    assert result.returncode == 69
    assert "did not resolve" in result.stderr


@pytest.mark.parametrize("target", ["server", ":5555", "server:"])
def test_resolve_servers_refuses_a_bad_target(tmp_path: Path, target: str) -> None:
    result = run_resolve_servers(tmp_path, ["10.0.0.1"], target, "echo", "train")
    assert result.returncode == 64
