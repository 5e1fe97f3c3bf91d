"""Watching the ego in sumo-gui: a view that follows it, a pace a person can follow, pictures.

`GuiView` says how; `Viewer` does it through the TraCI connection at `OverTraci`'s two hooks
(the ego is in a new episode; a decision's simulation steps are done). The pace is the bridge's,
not sumo-gui's own delay: that one would also slow the warm-up at reset and the leader's run-on
after the last step (minutes of simulated time), past the client's deadlines.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

VIEW_ID = "View #0"
"""sumo-gui's main view."""
DEFAULT_DELAY_MS = 100.0
"""Wall-clock ms per simulation step: real time at SUMO's 0.1 s step."""
DEFAULT_SPAN_M = 150.0
"""Metres of road across the window: the ego with its leader and follower at ~40 m."""
GIF_MAX_WIDTH = 640
"""The GIF's frames are scaled down to this width (the PNG frames keep the window's)."""
GIF_MAX_FRAMES = 500
"""Longer episodes keep every k-th frame in the GIF (still played in real time): Pillow holds
every frame in memory while it writes one."""
GIF_TIMEOUT_S = 120.0
"""Longest wait at close for the GIFs still being written."""

log = logging.getLogger("sim_server")


@dataclass(frozen=True)
class GuiView:
    """How sumo-gui shows an episode.

    The view follows the ego (`span_m` metres across the window, SUMO's "real world" schema:
    car shapes and lane markings) and paints it `ego_color`; each simulation step of an
    episode takes at least `delay_ms` of wall-clock time. With `screenshots`, every
    `screenshot_every`-th step is saved as a PNG in ``DIR/episode-NNNN/`` and the episode is
    assembled into ``DIR/episode-NNNN.gif`` (Pillow) once it is over.
    """

    delay_ms: float = DEFAULT_DELAY_MS
    span_m: float = DEFAULT_SPAN_M
    ego_color: tuple[int, int, int] = (255, 0, 0)
    schema: str = "real world"
    window: tuple[int, int] = (1024, 520)
    screenshots: Path | None = None
    screenshot_every: int = 1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.delay_ms) and self.delay_ms >= 0):
            raise ValueError(f"delay {self.delay_ms:g} ms: must be >= 0")
        if not (math.isfinite(self.span_m) and self.span_m > 0):
            raise ValueError(f"span {self.span_m:g} m: must be > 0")
        if self.screenshot_every < 1:
            raise ValueError(f"screenshot every {self.screenshot_every} steps: must be >= 1")
        if not all(0 <= c <= 255 for c in self.ego_color):
            raise ValueError(f"ego colour {self.ego_color}: RGB components in 0..255")

    def sumo_args(self) -> list[str]:
        """sumo-gui's command-line options for this view (its window size: the pictures')."""
        width, height = self.window
        return ["--window-size", f"{width},{height}"]


@dataclass
class _Episode:
    """The pictures of one episode: requested frames and their simulation times."""

    folder: Path
    frames: list[Path]
    times: list[float]
    pending: bool = False
    """The latest hook asked for a frame: sumo-gui draws it after the next simulation step,
    which is the episode's if another decision follows, and after its end if none does."""


class Viewer:
    """Applies a `GuiView` to sumo-gui over a TraCI connection (`api`)."""

    def __init__(self, view: GuiView) -> None:
        self.view = view
        self._dt = 0.1
        self._sim_time = 0.0
        self._due = 0.0
        self._steps = 0
        self._episode: _Episode | None = None
        self._writers: list[threading.Thread] = []

    def ego_ready(self, api: Any, ego_id: str) -> None:
        """A new episode: follow the ego at the view's span, colour it, start its pictures."""
        self.finish()
        gui = api.gui
        gui.setSchema(VIEW_ID, self.view.schema)
        zoom = gui.getZoom(VIEW_ID)
        (x_min, _), (x_max, _) = gui.getBoundary(VIEW_ID)
        gui.setZoom(VIEW_ID, zoom * (x_max - x_min) / self.view.span_m)  # width ~ 1 / zoom
        api.vehicle.setColor(ego_id, (*self.view.ego_color, 255))
        gui.setOffset(VIEW_ID, *api.vehicle.getPosition(ego_id))  # tracking starts at a redraw
        gui.trackVehicle(VIEW_ID, ego_id)
        self._dt = api.simulation.getDeltaT()
        self._sim_time = api.simulation.getTime()
        self._due = time.monotonic()
        self._steps = 0
        if self.view.screenshots is not None:
            self._episode = self._new_episode(self.view.screenshots)
            if self._episode is not None:
                self._shoot(api)

    def stepped(self, api: Any, ego_id: str) -> None:
        """After a decision: wait out the pace, take the step's picture if it is due."""
        self._pace(api.simulation.getTime())
        self._steps += 1
        episode = self._episode
        if episode is None:
            return
        episode.pending = False
        if self._steps % self.view.screenshot_every == 0 and ego_id in api.vehicle.getIDList():
            self._shoot(api)

    def _pace(self, sim_time: float) -> None:
        """Sleep until `delay_ms` per simulation step since the last decision has passed
        (time the learner took counts; a slow learner is not slowed further)."""
        steps = max(0.0, (sim_time - self._sim_time) / self._dt)
        self._sim_time = sim_time
        due = self._due + steps * self.view.delay_ms / 1000
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        self._due = max(due, now)

    def _new_episode(self, root: Path) -> _Episode | None:
        """Claim the next free ``episode-NNNN`` folder (several servers may share `root`)."""
        try:
            root.mkdir(parents=True, exist_ok=True)
            names = (p.name.partition(".")[0][8:] for p in root.glob("episode-*"))
            number = max((int(n) for n in names if n.isdigit()), default=0) + 1
            while True:
                folder = root / f"episode-{number:04d}"
                try:
                    folder.mkdir()
                    return _Episode(folder, [], [])
                except FileExistsError:
                    number += 1
        except OSError as exc:
            log.warning("no screenshots of this episode: %s", exc)
            return None

    def _shoot(self, api: Any) -> None:
        episode = self._episode
        assert episode is not None
        path = episode.folder / f"frame-{self._steps:05d}.png"
        api.gui.screenshot(VIEW_ID, str(path.resolve()))
        episode.frames.append(path)
        episode.times.append(api.simulation.getTime())
        episode.pending = True

    def finish(self) -> None:
        """The episode is over: drop its picture of the road after the end, write its GIF."""
        episode, self._episode = self._episode, None
        if episode is None:
            return
        if episode.pending:
            episode.times.pop()
            with contextlib.suppress(OSError):
                episode.frames.pop().unlink(missing_ok=True)
        if len(episode.frames) < 2:
            return
        gif = episode.folder.with_suffix(".gif")
        writer = threading.Thread(
            target=_write_gif_logged, args=(episode, gif), name=f"gif {gif.name}", daemon=True
        )
        writer.start()
        self._writers = [w for w in self._writers if w.is_alive()] + [writer]

    def close(self) -> None:
        """sumo-gui has quit: finish the episode and wait (bounded) for its GIF."""
        self.finish()
        deadline = time.monotonic() + GIF_TIMEOUT_S
        for writer in self._writers:
            writer.join(timeout=max(0.0, deadline - time.monotonic()))
            if writer.is_alive():
                log.warning("%s: not done within %.0f s", writer.name, GIF_TIMEOUT_S)
        self._writers = []


def _write_gif_logged(episode: _Episode, gif: Path) -> None:
    try:
        count = write_gif(episode.frames, episode.times, gif)
    except ImportError:
        log.warning("no GIF of %s: Pillow is not installed (pip install pillow)", episode.folder)
    except (OSError, ValueError) as exc:
        log.warning("no GIF of %s: %s", episode.folder, exc)
    else:
        log.info("episode pictures: %s, %s (%d frames)", episode.folder, gif, count)


def write_gif(frames: list[Path], times: list[float], gif: Path) -> int:
    """An animated GIF of `frames` (taken at simulation `times`) played in real time; at most
    `GIF_MAX_FRAMES` frames, `GIF_MAX_WIDTH` pixels wide. Frames sumo-gui did not write are
    skipped. Returns the number of frames in it."""
    from PIL import Image

    present = [(p, t) for p, t in zip(frames, times, strict=True) if p.is_file()]
    every = max(1, math.ceil(len(present) / GIF_MAX_FRAMES))
    kept = present[::every]
    if len(kept) < 2:
        raise ValueError(f"{len(kept)} frame(s) on disk, need 2")
    ends = [t for _, t in kept[1:]]
    ends.append(ends[-1] + (ends[-1] - kept[-2][1]))  # the last frame as long as the one before
    durations = [max(20, round((end - t) * 1000)) for (_, t), end in zip(kept, ends, strict=True)]
    images = []
    for path, _ in kept:
        with Image.open(path) as picture:
            image = picture.convert("RGB")
        if image.width > GIF_MAX_WIDTH:
            height = round(image.height * GIF_MAX_WIDTH / image.width)
            image = image.resize((GIF_MAX_WIDTH, height), Image.Resampling.LANCZOS)
        images.append(image.quantize(colors=64))
    partial = gif.with_name(gif.name + ".part")
    images[0].save(
        partial, format="GIF", save_all=True, append_images=images[1:], duration=durations, loop=0
    )
    partial.replace(gif)
    return len(images)
