"""A SUMO network as a graph of roads: what random trips and the ego's random routes are drawn
from.

`RoadGraph.read` parses a ``.net.xml`` (or ``.net.xml.gz``) once: every edge a passenger car
may drive (its length, lanes, speed limit and the junctions it joins) and which edges lead into
which (the network's connections). Trips are drawn within the largest strongly connected part
(`RoadGraph.connected`), so that every trip has a route and no ego is sent up a dead end it
cannot leave. The graph is cached as JSON beside the scenario files, keyed by the network's
content, so a server starts from it in a second the next time.
"""

from __future__ import annotations

import gzip
import hashlib
import heapq
import json
import math
import os
import random
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any
from xml.etree import ElementTree

PASSENGER = "passenger"
GRAPH_FORMAT = 1
"""Version of the cached graph's JSON (a change of this module's reading bumps it)."""
_NOT_ROADS = frozenset({"internal", "crossing", "walkingarea", "connector"})
"""Edge functions that are no road a car starts or ends a trip on."""


@dataclass(frozen=True, slots=True)
class Road:
    """One edge of the network a passenger car may drive."""

    id: str
    start: str
    """The junction it leaves."""
    end: str
    """The junction it leads to."""
    length: float
    lanes: int
    """Lanes a passenger car may use."""
    speed: float
    """Speed limit (m/s), of its fastest lane a car may use."""


@dataclass
class RoadGraph:
    """The roads of a network, which lead into which, and where its junctions are."""

    roads: dict[str, Road]
    successors: dict[str, list[str]]
    junctions: dict[str, tuple[float, float]]
    traffic_lights: int = 0
    """Junctions controlled by a traffic light."""

    @classmethod
    def read(cls, net_file: Path) -> RoadGraph:
        """Parse a SUMO network file (plain or gzipped XML)."""
        roads: dict[str, Road] = {}
        successors: dict[str, set[str]] = {}
        junctions: dict[str, tuple[float, float]] = {}
        lights = 0
        with _open(net_file) as stream:
            for _, element in ElementTree.iterparse(stream, events=("end",)):
                tag = element.tag
                if tag == "edge":
                    road = _road(element)
                    if road is not None:
                        roads[road.id] = road
                    element.clear()
                elif tag == "junction":
                    if element.get("type", "") != "internal":
                        junctions[element.get("id", "")] = (
                            float(element.get("x", "0")),
                            float(element.get("y", "0")),
                        )
                        lights += element.get("type", "") in (
                            "traffic_light",
                            "traffic_light_right_on_red",
                            "traffic_light_unregulated",
                        )
                    element.clear()
                elif tag == "connection":
                    source, target = element.get("from", ""), element.get("to", "")
                    if not source.startswith(":") and not target.startswith(":"):
                        successors.setdefault(source, set()).add(target)
                    element.clear()
        linked = {
            edge: sorted(t for t in targets if t in roads)
            for edge, targets in successors.items()
            if edge in roads
        }
        return cls(roads, linked, junctions, lights)

    @classmethod
    def cached(cls, net_file: Path, cache_dir: Path) -> RoadGraph:
        """`read`, or the graph cached for a network of the same content."""
        digest = file_digest(net_file)
        cache = cache_dir / "graphs" / f"{digest}-v{GRAPH_FORMAT}.json"
        if cache.is_file():
            try:
                return cls.from_json(json.loads(cache.read_text()))
            except (OSError, ValueError, KeyError, TypeError):
                pass  # rebuilt below
        graph = cls.read(net_file)
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(f"{cache.name}.tmp{os.getpid()}")
        tmp.write_text(json.dumps(graph.to_json()))
        tmp.replace(cache)
        return graph

    def to_json(self) -> dict[str, Any]:
        return {
            "roads": [
                [r.id, r.start, r.end, r.length, r.lanes, r.speed] for r in self.roads.values()
            ],
            "successors": self.successors,
            "junctions": self.junctions,
            "traffic_lights": self.traffic_lights,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> RoadGraph:
        roads = {
            str(i): Road(str(i), str(a), str(b), float(length), int(lanes), float(speed))
            for i, a, b, length, lanes, speed in data["roads"]
        }
        junctions = {k: (float(x), float(y)) for k, (x, y) in data["junctions"].items()}
        return cls(roads, dict(data["successors"]), junctions, int(data["traffic_lights"]))

    def connected(self) -> list[str]:
        """The roads of the largest strongly connected part (from each, every other can be
        reached), in a stable order."""
        largest: list[str] = []
        for part in _strongly_connected(self.successors, self.roads):
            if len(part) > len(largest):
                largest = part
        return sorted(largest)

    def reachable(self, roads: list[str], forward: bool = True) -> list[str]:
        """The roads reachable from `roads` (`forward`), or from which they are reachable
        (`forward` False), `roads` included, in a stable order."""
        links = self.successors if forward else self._predecessors()
        seen = set(roads)
        frontier = list(roads)
        while frontier:
            road = frontier.pop()
            for other in links.get(road, ()):
                if other not in seen:
                    seen.add(other)
                    frontier.append(other)
        return sorted(seen)

    def _predecessors(self) -> dict[str, list[str]]:
        found: dict[str, list[str]] = {}
        for road, followers in self.successors.items():
            for follower in followers:
                found.setdefault(follower, []).append(road)
        return found

    def lane_km(self, roads: list[str]) -> float:
        """Kilometres of lane of `roads`."""
        return sum(self.roads[r].lanes * self.roads[r].length for r in roads) / 1000.0

    def distances(self, source: str, allowed: set[str], limit: float) -> dict[str, float]:
        """Metres from the start of `source` to the end of each road of `allowed` reachable
        within `limit` (shortest by length: Dijkstra over the roads)."""
        first = self.roads[source].length
        best = {source: first}
        queue = [(first, source)]
        while queue:
            distance, road = heapq.heappop(queue)
            if distance > best.get(road, math.inf) or distance > limit:
                continue
            for follower in self.successors.get(road, ()):
                if follower not in allowed:
                    continue
                candidate = distance + self.roads[follower].length
                if candidate < best.get(follower, math.inf):
                    best[follower] = candidate
                    heapq.heappush(queue, (candidate, follower))
        return best

    def straight_distance(self, a: str, b: str) -> float:
        """Metres between the start of road `a` and the end of road `b`, as the crow flies."""
        x1, y1 = self.junctions.get(self.roads[a].start, (0.0, 0.0))
        x2, y2 = self.junctions.get(self.roads[b].end, (0.0, 0.0))
        return math.hypot(x2 - x1, y2 - y1)


def weighted_roads(
    graph: RoadGraph, roads: list[str], draw: random.Random, count: int
) -> list[str]:
    """`count` roads drawn from `roads`, each as likely as its lane-kilometres."""
    weights = [graph.roads[r].lanes * graph.roads[r].length for r in roads]
    return draw.choices(roads, weights=weights, k=count)


def file_digest(path: Path) -> str:
    """A short hash of a file's content."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def _open(path: Path) -> IO[bytes]:
    with path.open("rb") as probe:
        gzipped = probe.read(2) == b"\x1f\x8b"
    if gzipped:
        return gzip.GzipFile(path, "rb")  # type: ignore[return-value]
    return path.open("rb")


def _road(element: ElementTree.Element) -> Road | None:
    """An edge a passenger car may drive, or None."""
    if element.get("function", "normal") in _NOT_ROADS or element.get("id", "").startswith(":"):
        return None
    usable = [lane for lane in element.iter("lane") if _allows_cars(lane)]
    if not usable:
        return None
    return Road(
        id=element.get("id", ""),
        start=element.get("from", ""),
        end=element.get("to", ""),
        length=float(usable[0].get("length", "0")),
        lanes=len(usable),
        speed=max(float(lane.get("speed", "13.89")) for lane in usable),
    )


def _allows_cars(lane: ElementTree.Element) -> bool:
    allow = lane.get("allow")
    if allow is not None:
        return PASSENGER in allow.split() or "all" in allow.split()
    disallow = lane.get("disallow", "")
    return PASSENGER not in disallow.split() and "all" not in disallow.split()


def _strongly_connected(
    successors: dict[str, list[str]], nodes: dict[str, Road]
) -> Iterator[list[str]]:
    """Tarjan's strongly connected components, iteratively (no recursion limit on large
    networks)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    counter = 0
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(successors.get(root, ())))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            advanced = False
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(successors.get(child, ()))))
                    advanced = True
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            if advanced:
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                yield component
