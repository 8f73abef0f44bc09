"""The pixels of a tile database, wherever they are: its PNGs or windows of its map (one small object a worker
process can be sent)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from aeroloc.core.images import read_image
from aeroloc.maps.sources import Map
from aeroloc.maps.tiling import load_info, load_tiles
from aeroloc.maps.windows import open_checked, read_windows


class TileSource:
    """The pixels of a tile database: its images when they were written (``--write-images``, and every format-1
    database), else windows of the map it records (checked unchanged before the first read).

    Picklable and small: a worker process gets the folder and reloads ``tiles.csv`` itself."""

    def __init__(self, folder, tiles: list | None = None, info: dict | None = None):
        self.folder = Path(folder)
        self._tiles, self._info, self._map = tiles, info, None

    @property
    def tiles(self) -> list:
        if self._tiles is None:
            self._tiles = load_tiles(self.folder)
        return self._tiles

    @property
    def info(self) -> dict:
        if self._info is None:
            self._info = load_info(self.folder)
        return self._info

    @property
    def has_images(self) -> bool:
        return bool(self.info.get("images", True))

    def map(self) -> Map:
        if self._map is None:
            self._map = open_checked(self.info["map"], self.tiles)
        return self._map

    def image(self, position: int) -> np.ndarray:
        """RGB uint8 of tile ``position`` (its tiles.csv row)."""
        t = self.tiles[position]
        if self.has_images:
            return read_image(self.folder / t.path)
        rgb, _ = self.map().read(t.col, t.row, t.width, t.height)
        return rgb

    def images(self, start: int, stop: int) -> Iterator[np.ndarray]:
        """Tiles ``start`` .. ``stop`` - 1 in order, windows cut from band reads of the map."""
        if self.has_images:
            yield from (self.image(i) for i in range(start, stop))
        else:
            yield from read_windows(self.map(), self.tiles[start:stop])

    def __getstate__(self):
        return {"folder": self.folder, "_tiles": None, "_info": None, "_map": None}


__all__ = ["TileSource"]
