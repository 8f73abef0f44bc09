"""The tiles beside a retrieved one: candidates retrieval ranks just out of reach.

Tiles overlap (the atlas: by half), so a photo lying across the border of its best tile is also partly in that
tile's neighbour, and retrieval may rank the neighbour first and the tile that holds the photo best nowhere in the
top N (NAIP flight, frames just after an outage: the neighbour 1st or 2nd, the best tile out of the list; matched
against that tile, the frame gives 31-46 inliers instead of 3-5). The neighbours of the first retrieved tiles are
a few candidates, where a deeper list is many.

:class:`Neighbourhood` buckets the tiles by their centres once, so a lookup reads a few buckets whatever the map's
size: the ring beside a tile (:meth:`Neighbourhood.around`) and the tiles that hold a point
(:meth:`Neighbourhood.containing`, where a dense or swept fix lies).
"""

from __future__ import annotations

import math
from collections import defaultdict


class Neighbourhood:
    """Tiles by their centres (map px), in square buckets of the smallest tile side."""

    def __init__(self, tiles):
        self.cell = float(min((min(t.width, t.height) for t in tiles), default=1))
        self.buckets: dict[tuple[int, int], list] = defaultdict(list)  # key -> [(order, tile)]
        self.half_w = self.half_h = 0.0  # the widest and tallest tile's half side: how far a holder's centre lies
        for i, t in enumerate(tiles):
            self.buckets[self._key(*_centre(t))].append((i, t))
            self.half_w, self.half_h = max(self.half_w, t.width / 2), max(self.half_h, t.height / 2)

    def _key(self, x: float, y: float) -> tuple[int, int]:
        return int(math.floor(x / self.cell)), int(math.floor(y / self.cell))

    def around(self, tile, k: int = 8) -> list:
        """The ``k`` tiles nearest ``tile`` (by centre) among those that overlap or touch it (centres at most one
        tile side apart on each axis), not ``tile`` itself, nearest first: the ring of 8 beside it on a grid with
        or without overlap."""
        cx, cy = _centre(tile)
        reach_x, reach_y = tile.width, tile.height
        kx, ky = self._key(cx, cy)
        nx, ny = int(math.ceil(reach_x / self.cell)) + 1, int(math.ceil(reach_y / self.cell)) + 1
        near = []  # (squared centre distance, id, tile)
        for i in range(kx - nx, kx + nx + 1):
            for j in range(ky - ny, ky + ny + 1):
                for _, t in self.buckets.get((i, j), ()):
                    dx, dy = _centre(t)[0] - cx, _centre(t)[1] - cy
                    if t.id != tile.id and abs(dx) <= reach_x + 0.5 and abs(dy) <= reach_y + 0.5:
                        near.append((dx * dx + dy * dy, t.id, t))
        return [t for *_, t in sorted(near, key=lambda n: n[:2])[:k]]

    def containing(self, x: float, y: float) -> list:
        """Every tile whose pixels hold the point (``x``, ``y``) (map px, edges included), nearest centre first;
        ties in the order the tiles were given. Reads the buckets within half the largest tile of the point: a
        few on any map, where a scan of every tile grows with the map (a country-size database: 10^6 tiles)."""
        kx0, ky0 = self._key(x - self.half_w, y - self.half_h)
        kx1, ky1 = self._key(x + self.half_w, y + self.half_h)
        inside = []  # (squared centre distance, order, tile)
        for i in range(kx0, kx1 + 1):
            for j in range(ky0, ky1 + 1):
                for order, t in self.buckets.get((i, j), ()):
                    if t.col <= x <= t.col + t.width and t.row <= y <= t.row + t.height:
                        cx, cy = _centre(t)
                        inside.append(((cx - x) ** 2 + (cy - y) ** 2, order, t))
        return [t for *_, t in sorted(inside, key=lambda n: n[:2])]


def neighbour_candidates(near: Neighbourhood, by_id: dict, seeds: list[str], tried: set[str]) -> list[str]:
    """The neighbours of the ``seeds`` tiles (in the seeds' order, each seed's nearest first) not in ``tried``."""
    out: list[str] = []
    seen = set(tried)
    for s in seeds:
        for t in near.around(by_id[s]):
            if t.id not in seen:
                seen.add(t.id)
                out.append(t.id)
    return out


def _centre(t) -> tuple[float, float]:
    return t.col + t.width / 2, t.row + t.height / 2
