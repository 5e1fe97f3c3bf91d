"""Watching the ego in sumo-gui (`sim_server/backends/sumo/gui.py`).

The command line and the viewer's logic are tested without a display (a stand-in for the TraCI
connection); a real sumo-gui runs under an Xvfb this module starts, skipped without Xvfb.
"""

from __future__ import annotations

import os
import select
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from sim_server import cli
from sim_server.backends.sumo import gui as gui_module
from sim_server.backends.sumo.gui import VIEW_ID, GuiView, Viewer, write_gif

Image = pytest.importorskip("PIL.Image")

XVFB_START_TIMEOUT_S = 30.0


# --------------------------------------------------------------------------- the command line


def refusal(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """sim-server's one-line refusal of `argv` (exit status 2)."""
    assert cli.main(["--bind", "tcp://127.0.0.1:0", *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith("sim-server: error: "), err
    return err.removeprefix("sim-server: error: ")


@pytest.mark.parametrize(
    ("flag", "value"),
    [
        ("--gui-delay", "50"),
        ("--gui-span", "100"),
        ("--screenshots", "shots"),
        ("--screenshot-every", "2"),
    ],
)
def test_each_view_option_needs_gui(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, flag: str, value: str
) -> None:
    value = str(tmp_path / value) if flag == "--screenshots" else value
    assert (
        refusal(capsys, "--backend", "sumo-traci", flag, value)
        == f"{flag} needs --gui (with --backend sumo-traci)\n"
    )
    assert not (tmp_path / "shots").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--gui-delay", "-1"], "--gui-delay -1: must be >= 0 ms"),
        (["--gui-delay", "nan"], "--gui-delay nan: must be >= 0 ms"),
        (["--gui-span", "0"], "--gui-span 0: must be > 0 m"),
        (["--screenshot-every", "2"], "--screenshot-every 2: needs --screenshots DIR"),
        (
            ["--screenshots", "{tmp}", "--screenshot-every", "0"],
            "--screenshot-every 0: must be at least 1",
        ),
    ],
)
def test_bad_view_values_are_refused_before_anything_starts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, argv: list[str], message: str
) -> None:
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert refusal(capsys, "--backend", "sumo-traci", "--gui", *argv) == message + "\n"


def test_screenshots_must_be_a_folder(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    taken = tmp_path / "a-file"
    taken.write_text("")
    message = refusal(capsys, "--backend", "sumo-traci", "--gui", "--screenshots", str(taken))
    assert message.startswith(f"--screenshots {taken}: ")


def test_gui_without_sumo_traci_is_still_refused_first(capsys: pytest.CaptureFixture[str]) -> None:
    message = refusal(capsys, "--backend", "sumo", "--gui", "--gui-delay", "50")
    assert message == "--gui needs --backend sumo-traci, not --backend sumo\n"


def test_the_command_line_builds_the_view(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    built: list[dict[str, Any]] = []

    def backend(**kw: Any) -> dict[str, Any]:
        built.append(kw)
        return kw

    monkeypatch.setattr("sim_server.backends.sumo.backend.SumoBackend", backend)
    parser = cli.build_parser()
    cli.make_backend(parser.parse_args(["--backend", "sumo-traci", "--gui"]))
    assert built[-1]["view"] == GuiView()  # following the ego is the default, not an option
    shots = tmp_path / "new" / "shots"
    argv = ["--backend", "sumo-traci", "--gui", "--gui-delay", "0", "--gui-span", "80"]
    args = parser.parse_args([*argv, "--screenshots", str(shots), "--screenshot-every", "3"])
    cli.check_usage(args)
    assert shots.is_dir()  # made before anything starts
    cli.make_backend(args)
    assert built[-1]["view"] == GuiView(
        delay_ms=0.0, span_m=80.0, screenshots=shots.resolve(), screenshot_every=3
    )
    cli.make_backend(parser.parse_args(["--backend", "sumo-traci"]))
    assert built[-1]["view"] is None


def test_view_values_are_checked() -> None:
    with pytest.raises(ValueError, match="delay"):
        GuiView(delay_ms=-1)
    with pytest.raises(ValueError, match="span"):
        GuiView(span_m=0)
    with pytest.raises(ValueError, match="every"):
        GuiView(screenshot_every=0)
    with pytest.raises(ValueError, match="colour"):
        GuiView(ego_color=(0, 0, 256))


# --------------------------------------------------------------------------- the viewer, no SUMO


class FakeSumoGui:
    """What `Viewer` uses of a TraCI connection to sumo-gui: simulation time advances with
    `advance`, a screenshot is written (a plain picture) at the next step, as sumo-gui does."""

    def __init__(self) -> None:
        self.time = 30.0
        self.vehicles = ["ego", "h1"]
        self.calls: list[tuple[Any, ...]] = []
        self.pending: list[str] = []
        self.gui = SimpleNamespace(
            DEFAULT_VIEW=VIEW_ID,
            setSchema=lambda v, s: self.calls.append(("schema", v, s)),
            getZoom=lambda v: 100.0,
            getBoundary=lambda v: ((-5.0, -200.0), (1995.0, 200.0)),
            setZoom=lambda v, z: self.calls.append(("zoom", v, z)),
            setOffset=lambda v, x, y: self.calls.append(("offset", v, x, y)),
            trackVehicle=lambda v, i: self.calls.append(("track", v, i)),
            screenshot=lambda v, path: self.pending.append(path),
        )
        self.vehicle = SimpleNamespace(
            setColor=lambda i, c: self.calls.append(("color", i, c)),
            getIDList=lambda: tuple(self.vehicles),
            getPosition=lambda i: (120.0, -1.6),
        )
        self.simulation = SimpleNamespace(getDeltaT=lambda: 0.1, getTime=lambda: self.time)

    def advance(self, steps: int = 1) -> None:
        self.time += 0.1 * steps
        for path in self.pending:
            Image.new("RGB", (1000, 300), (round(self.time * 10) % 256, 90, 30)).save(path)
        self.pending = []


def test_viewer_follows_the_ego_at_its_span(tmp_path: Path) -> None:
    api = FakeSumoGui()
    Viewer(GuiView(span_m=200.0)).ego_ready(api, "ego")
    assert ("schema", VIEW_ID, "real world") in api.calls
    assert ("zoom", VIEW_ID, pytest.approx(100.0 * 2000.0 / 200.0)) in api.calls  # 2000 m -> 200 m
    assert ("color", "ego", (255, 0, 0, 255)) in api.calls
    assert ("offset", VIEW_ID, 120.0, -1.6) in api.calls  # centred at once, then tracked
    assert ("track", VIEW_ID, "ego") in api.calls


def test_viewer_paces_the_steps_counting_the_learners_time() -> None:
    api = FakeSumoGui()
    viewer = Viewer(GuiView(delay_ms=50.0))
    viewer.ego_ready(api, "ego")
    started = time.monotonic()
    for _ in range(4):
        api.advance(2)  # a 0.2 s decision: two simulation steps, 2 x 50 ms
        viewer.stepped(api, "ego")
    assert 0.4 <= time.monotonic() - started < 1.5
    time.sleep(0.3)  # a slow learner: 3 steps' worth of time has passed already
    api.advance(3)
    started = time.monotonic()
    viewer.stepped(api, "ego")
    assert time.monotonic() - started < 0.05


def test_viewer_pictures_an_episode_without_the_frame_after_its_end(tmp_path: Path) -> None:
    api = FakeSumoGui()
    viewer = Viewer(GuiView(delay_ms=0.0, screenshots=tmp_path, screenshot_every=2))
    (tmp_path / "episode-0007").mkdir()  # a folder of an earlier run: numbering goes on
    viewer.ego_ready(api, "ego")
    for _ in range(10):
        api.advance()
        viewer.stepped(api, "ego")
    api.advance(300)  # the next reset's warm-up: sumo-gui draws frame 10, after the end
    viewer.ego_ready(api, "ego")  # the next episode: the first one's GIF
    api.advance()
    viewer.close()  # the second has one frame, drawn after its end: dropped, no GIF
    frames = sorted(p.name for p in (tmp_path / "episode-0008").iterdir())
    assert frames == [f"frame-{k:05d}.png" for k in (0, 2, 4, 6, 8)]  # 10: after the end
    with Image.open(tmp_path / "episode-0008.gif") as gif:
        assert gif.n_frames == 5
        assert gif.width == gui_module.GIF_MAX_WIDTH
        assert gif.info["duration"] == 200  # real time: 2 steps of 0.1 s per frame
    assert list((tmp_path / "episode-0009").iterdir()) == []
    assert not (tmp_path / "episode-0009.gif").exists()


def test_a_folder_that_cannot_be_made_costs_the_pictures_not_the_episode(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    api = FakeSumoGui()
    (tmp_path / "taken").write_text("")
    viewer = Viewer(GuiView(delay_ms=0.0, screenshots=tmp_path / "taken" / "shots"))
    viewer.ego_ready(api, "ego")
    api.advance()
    viewer.stepped(api, "ego")
    viewer.close()
    assert api.pending == []
    assert "no screenshots of this episode" in caplog.text


def test_gif_of_a_long_episode_keeps_every_kth_frame(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(gui_module, "GIF_MAX_FRAMES", 4)
    frames = []
    for k in range(10):
        frames.append(tmp_path / f"f{k}.png")
        Image.new("RGB", (320, 100), (25 * k, 0, 0)).save(frames[-1])
    frames.insert(3, tmp_path / "never-written.png")
    times = [0.1 * k for k in range(11)]
    assert write_gif(frames, times, tmp_path / "a.gif") == 4  # 10 on disk, every 3rd
    with Image.open(tmp_path / "a.gif") as gif:
        assert gif.n_frames == 4
        assert gif.size == (320, 100)
    with pytest.raises(ValueError, match="need 2"):
        write_gif(frames[:1], times[:1], tmp_path / "b.gif")


# --------------------------------------------------------------------------- a real sumo-gui


@pytest.fixture(scope="module")
def display() -> Iterator[str]:
    """An X server of our own (Xvfb) on a free display number, ready when it says so."""
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("Xvfb is not installed (apt-get install xvfb): no display for sumo-gui")
    from sim_server.backends.sumo.runtime import find_sumo_binary

    try:
        find_sumo_binary(gui=True)
    except FileNotFoundError:
        pytest.skip("no sumo-gui binary")
    read, write = os.pipe()
    command = [xvfb, "-displayfd", str(write), "-screen", "0", "1280x800x24", "-nolisten", "tcp"]
    process = subprocess.Popen(
        command, pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    os.close(write)
    try:
        number = b""
        deadline = time.monotonic() + XVFB_START_TIMEOUT_S
        while not number.endswith(b"\n"):  # Xvfb writes the display number once it accepts
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([read], [], [], left)[0]:
                pytest.fail(f"Xvfb gave no display number within {XVFB_START_TIMEOUT_S:.0f} s")
            chunk = os.read(read, 16)
            if not chunk:
                pytest.fail(f"Xvfb exited with code {process.wait(timeout=10)} during start-up")
            number += chunk
        yield f":{number.decode().strip()}"
    finally:
        os.close(read)
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)


def red_pixels(picture: Any) -> Any:
    """The ego's pixels (painted pure red) as a mask."""
    import numpy as np

    rgb = np.asarray(picture.convert("RGB")).astype(int)
    return (rgb[..., 0] > 200) & (rgb[..., 1] < 60) & (rgb[..., 2] < 60)


@pytest.mark.sumo
@pytest.mark.slow
def test_sumo_gui_follows_the_ego_and_pictures_the_episode(
    display: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import numpy as np

    from sim_server.backends.sumo.backend import SumoBackend
    from sim_server.backends.sumo.scenarios import EGO_ID

    monkeypatch.setenv("DISPLAY", display)
    monkeypatch.setenv("HOME", str(tmp_path))  # sumo-gui keeps its settings in ~/.foxrc
    shots = tmp_path / "shots"
    view = GuiView(delay_ms=20.0, span_m=150.0, screenshots=shots)
    backend = SumoBackend(cache_dir=tmp_path / "cache", traci=True, gui=True, view=view)
    try:
        info = {s.name: s for s in backend.scenarios()}["cf"]
        obs = backend.reset("cf", 3, {**info.options, "max_episode_time": 3.0})
        api = backend._api  # the TraCI connection to sumo-gui, to read its view
        started, seq, offsets = time.monotonic(), 0, []
        while not (obs.terminated or obs.truncated):
            seq += 1
            obs = backend.step(seq, 0.0, 0)
            if seq % 10 == 0 and EGO_ID in api.vehicle.getIDList():
                (x0, _), (x1, _) = api.gui.getBoundary(VIEW_ID)
                offsets.append(
                    (api.gui.getOffset(VIEW_ID), api.vehicle.getPosition(EGO_ID), x1 - x0)
                )
        took = time.monotonic() - started
        assert obs.truncated and seq == 30  # 3 s of 0.1 s steps
        assert took >= seq * 0.020  # paced: 20 ms per simulation step at least
        assert len(offsets) >= 2
        for (x, y), (ego_x, ego_y), width in offsets:  # the view is centred on the ego...
            assert abs(x - ego_x) < 5.0 and abs(y - ego_y) < 5.0
            assert width == pytest.approx(150.0, rel=0.02)  # ...150 m across
        assert offsets[-1][1][0] - offsets[0][1][0] > 10.0  # and it moved with it
        backend.reset("cf", 4, {**info.options, "max_episode_time": 0.5})  # the 1st one's GIF
        for seq in range(1, 6):
            backend.step(seq, 0.0, 0)
    finally:
        backend.close()  # sumo-gui quits; the GIFs are waited for

    frames = sorted((shots / "episode-0001").glob("frame-*.png"))
    assert len(frames) == 30  # frames 0-29; the one asked for at step 30 shows the road after
    for path in frames[:: len(frames) // 5]:
        with Image.open(path) as picture:
            pixels = np.asarray(picture.convert("L"), dtype=float)
            assert picture.width >= 800  # the window's canvas (--window-size 1024,520)
            assert pixels.std() > 10  # a real picture: road, grass, vehicles, not one colour
            ego = red_pixels(picture)
            assert ego.sum() > 50  # the ego, painted red, is in it...
            columns = np.nonzero(ego.any(axis=0))[0]
            centre = (columns.min() + columns.max()) / 2
            assert abs(centre - picture.width / 2) < picture.width * 0.1  # ...in the middle
    for number, least in ((1, 25), (2, 4)):
        with Image.open(shots / f"episode-{number:04d}.gif") as gif:
            assert gif.n_frames >= least
            gif.seek(gif.n_frames // 2)
            assert red_pixels(gif).sum() > 10
