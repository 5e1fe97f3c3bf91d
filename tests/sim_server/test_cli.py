"""``sim-server`` usage errors: one line naming the bad value, exit status 2, no traceback.

Only refusals run here (in-process, nothing is bound); serving is tested over real processes in
tests/integration.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from sim_server import cli

LOOPBACK = ["--bind", "tcp://127.0.0.1:0"]


def refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """The one line `sim-server argv` printed on stderr when it refused to start."""
    status: object
    try:
        status = cli.main(argv)
    except SystemExit as exit_:  # argparse's own errors
        status = exit_.code
    assert status == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(("sim-server: error: ", "sim-server keygen: error: "))
    return lines[0]


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--backend", "nope"], ["'nope'", "'sumo'", "'sumo-traci'", "'fake'", "'highway'"]),
        (["--bind", "udp://x:1"], ["--bind 'udp://x:1'", "tcp://HOST:PORT", "ipc://PATH"]),
        (["--bind", "tcp://127.0.0.1:70000"], ["tcp://127.0.0.1:70000", "0..65535"]),
        (["--log-level", "loud"], ["'LOUD'", "'DEBUG'", "'WARNING'"]),
        ([*LOOPBACK, "--backend", "fake", "--gui"], ["--gui needs --backend sumo-traci", "fake"]),
        ([*LOOPBACK, "--traci-port", "8813"], ["--traci-port needs --backend sumo-traci"]),
        ([*LOOPBACK, "--backend", "sumo-traci", "--traci-port", "0"], ["--traci-port 0"]),
        ([*LOOPBACK, "--sumocfg", "/no/such.sumocfg"], ["--sumocfg /no/such.sumocfg: no such"]),
        ([*LOOPBACK, "--ego-route", "r0"], ["--ego-route r0", "--sumocfg"]),
        ([*LOOPBACK, "--osm", "/no/such.osm"], ["--osm /no/such.osm: no such file"]),
        ([*LOOPBACK, "--net", "/no/such.net.xml"], ["--net /no/such.net.xml: no such file"]),
        ([*LOOPBACK, "--scenario-name", "x"], ["--scenario-name x", "--net", "--osm"]),
        ([*LOOPBACK, "--backend", "replay"], ["--backend replay needs --recording DIR"]),
        ([*LOOPBACK, "--recording", "/no/such"], ["--recording needs --backend replay", "sumo"]),
        (
            [*LOOPBACK, "--backend", "replay", "--recording", "/no/such/rec"],
            ["--recording /no/such/rec: no such folder"],
        ),
        ([*LOOPBACK, "--workers", "0"], ["--workers 0"]),
        ([*LOOPBACK, "--pool", "0"], ["--pool 0"]),
        ([*LOOPBACK, "--pool", "2", "--workers", "2"], ["--pool and --workers"]),
        (["--bind", "direct://127.0.0.1:0", "--pool", "2"], ["--pool 2", "direct://", "--workers"]),
        (
            [*LOOPBACK, "--backend", "sumo-traci", "--traci-port", "8813", "--pool", "2"],
            ["--pool 2", "--traci-port"],
        ),
        ([*LOOPBACK, "--p", "2"], ["--p"]),  # no abbreviations: the pool's children get argv
        (["--bind", "tcp://127.0.0.1:65535", "--workers", "2"], ["--workers 2", "65535"]),
        ([*LOOPBACK, "--spin-us", "10"], ["--spin-us", "--bind tcp://127.0.0.1:0"]),
        ([*LOOPBACK, "--max-frame-bytes", "0"], ["--max-frame-bytes 0"]),
        ([*LOOPBACK, "--heartbeat-timeout", "-1"], ["--heartbeat-timeout -1"]),
        (["--bind", "tcp://0.0.0.0:0"], ["--bind tcp://0.0.0.0:0", "--secret-key", "--insecure"]),
        (["--bind", "direct://0.0.0.0:0", "--insecure"], ["--bind direct://0.0.0.0:0", "loopback"]),
        (
            [*LOOPBACK, "--secret-key", "/no/such.key_secret"],
            ["--secret-key", "/no/such.key_secret"],
        ),
        ([*LOOPBACK, "--authorized-keys", "/tmp"], ["--authorized-keys /tmp needs --secret-key"]),
        (["keygen"], ["--out"]),
    ],
)
def test_a_bad_command_line_is_one_line_naming_the_value(
    argv: list[str], expected: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    line = refused(argv, capsys)
    for part in expected:
        assert part in line, line


def test_a_sumocfg_needs_a_sumo_backend_and_an_ego_route(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "mine.sumocfg"
    config.write_text("<configuration/>\n")
    line = refused([*LOOPBACK, "--backend", "fake", "--sumocfg", str(config)], capsys)
    assert "--sumocfg needs a SUMO backend" in line and "fake" in line
    line = refused([*LOOPBACK, "--sumocfg", str(config)], capsys)
    assert "--ego-route" in line


def test_a_map_is_one_per_server_on_sumo_and_a_broken_one_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    net, osm = tmp_path / "a.net.xml", tmp_path / "b.osm"
    net.write_text("<net/>\n")
    osm.write_text("this is no OpenStreetMap export\n")
    line = refused([*LOOPBACK, "--net", str(net), "--osm", str(osm)], capsys)
    assert "--net" in line and "--osm" in line and "one map per server" in line
    line = refused([*LOOPBACK, "--backend", "highway", "--net", str(net)], capsys)
    assert "--net needs a SUMO backend" in line
    line = refused([*LOOPBACK, "--net", str(net), "--ego-route", "r"], capsys)
    assert "--ego-route r: applies to --sumocfg only" in line and "ego_from" in line
    line = refused([*LOOPBACK, "--net", str(net), "--cache-dir", str(tmp_path / "c")], capsys)
    assert f"--net {net}" in line and "no road a passenger car may drive" in line
    line = refused([*LOOPBACK, "--osm", str(osm), "--cache-dir", str(tmp_path / "c")], capsys)
    assert f"--osm {osm}: netconvert could not import" in line


def test_a_folder_without_a_recording_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    line = refused([*LOOPBACK, "--backend", "replay", "--recording", str(tmp_path)], capsys)
    assert f"--recording {tmp_path}: holds no recording (no manifest.json)" in line
    (tmp_path / "manifest.json").write_text(
        '{"format": "av-bridge-recording", "format_version": 1, "complete": true}'
    )
    (tmp_path / "session-000.avbr").write_bytes(b"AVBREC\x00\x01\x3e\xff")
    line = refused([*LOOPBACK, "--backend", "replay", "--recording", str(tmp_path)], capsys)
    assert "session-000.avbr: truncated record header" in line


@pytest.mark.parametrize(
    ("backend", "module", "package", "extra", "importers"),
    [
        ("highway", "highway_env", "highway-env", "highway", ["highway"]),
        ("sumo", "libsumo", "libsumo", "server", ["sumo.backend", "sumo.runtime"]),
    ],
)
def test_a_backend_that_is_not_installed_says_what_to_install(
    backend: str,
    module: str,
    package: str,
    extra: str,
    importers: list[str],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    prefixes = tuple(f"sim_server.backends.{name}" for name in importers)
    for cached in [m for m in sys.modules if m.startswith(prefixes)]:  # afresh, with submodules
        monkeypatch.delitem(sys.modules, cached)
    monkeypatch.setitem(sys.modules, module, None)  # as if not installed
    line = refused([*LOOPBACK, "--backend", backend], capsys)
    assert f"--backend {backend} needs {package}" in line
    assert f"pip install -e '.[{extra}]'" in line


def test_a_good_command_line_passes_the_checks() -> None:
    args = cli.build_parser().parse_args(
        ["--bind", "direct://127.0.0.1:0", "--backend", "fake", "--spin-us", "0"]
    )
    endpoint, credentials = cli.check_usage(args)
    assert endpoint.scheme == "direct" and credentials is None
    assert args.log_level == "INFO"
    assert cli.build_parser().parse_args(["--log-level", "warning"]).log_level == "WARNING"
