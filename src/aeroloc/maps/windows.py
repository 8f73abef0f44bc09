"""Tiles as windows of the map: the pixels of a tile database are read from the map when needed, not copied.

A country-size map has ~10^7 tiles; one PNG each is a few hundred GB of copies and a PNG encode per tile. Instead
the database records which map it was cut from (:func:`map_reference`: path, size, CRS, transform and a hash of
the pixels of sample windows) and reads tiles back through the same :class:`~aeroloc.maps.sources.Map`. A run of
tiles (a shard) is read as few large windows (:func:`read_windows`: one per band of tile rows with the same
column span), so each block of the map is decoded once, not once per tile that overlaps it.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator, Sequence
from itertools import groupby

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.maps.sources import Map, open_map

SAMPLE_WINDOWS = 16  # windows hashed into the map reference (cheap: a country map is never read in full to check)


def content_hash(m: Map, tiles: Sequence) -> str:
    """SHA-1 of what the grid reads, sampled: the decoded pixels of up to ``SAMPLE_WINDOWS`` evenly spaced tiles
    of a raster (a COG decodes a window in ~1 ms), or the bytes of as many evenly spaced raw tile files of a tile
    folder (decoding 1280 px PNGs to check would cost as much as the whole grid)."""
    h = hashlib.sha1()
    cells = getattr(m, "cells", None)
    if cells is not None:
        files = [cells[k] for k in sorted(cells)]
        for i in np.unique(np.linspace(0, len(files) - 1, min(SAMPLE_WINDOWS, len(files))).astype(int)):
            h.update(files[int(i)].read_bytes())
        return h.hexdigest()
    if not tiles:
        return h.hexdigest()
    for i in np.unique(np.linspace(0, len(tiles) - 1, min(SAMPLE_WINDOWS, len(tiles))).astype(int)):
        t = tiles[int(i)]
        rgb, _ = m.read(t.col, t.row, t.width, t.height)
        h.update(np.ascontiguousarray(rgb).tobytes())
    return h.hexdigest()


def map_reference(m: Map, tiles: Sequence) -> dict:
    """What tiles.json records about the map so a later read can tell it is the same one."""
    return {
        "path": str(m.path),
        "kind": type(m).__name__,
        "width": m.width,
        "height": m.height,
        "crs": m.crs,
        "transform": list(m.transform)[:6],
        "content_sha1": content_hash(m, tiles),
    }


def open_checked(ref: dict, tiles: Sequence) -> Map:
    """The map ``ref`` names, refused (one line) when its size, CRS, transform or sampled pixels changed."""
    path = ref.get("path")
    m = open_map(path)
    now = {"width": m.width, "height": m.height, "crs": m.crs, "transform": list(m.transform)[:6]}
    for key, value in now.items():
        if key in ref and ref[key] != value:
            raise AerolocError(
                f"{path}: the map changed since the tile grid was made ({key} {ref[key]} -> {value}); rebuild the database"
            )
    if ref.get("content_sha1") and content_hash(m, tiles) != ref["content_sha1"]:
        raise AerolocError(f"{path}: the map's pixels changed since the tile grid was made; rebuild the database")
    return m


def _bands(tiles: Sequence) -> Iterator[list[int]]:
    """Positions in ``tiles`` grouped into bands read as one window: consecutive tile rows (same ``row``) with
    the same column span merge, so a shard of whole grid rows is one read and a shard inside one wide grid row
    of a country map is a strip of it."""
    rows = [list(g) for _, g in groupby(range(len(tiles)), key=lambda i: tiles[i].row)]
    band: list[int] = []
    span = None
    for r in rows:
        s = (min(tiles[i].col for i in r), max(tiles[i].col + tiles[i].width for i in r))
        if band and s != span:
            yield band
            band = []
        band, span = band + r, s
    if band:
        yield band


def read_windows(m: Map, tiles: Sequence) -> Iterator[np.ndarray]:
    """RGB uint8 of each tile in order (the same pixels as ``m.read`` of its window), cut from band reads."""
    for band in _bands(tiles):
        c0 = min(tiles[i].col for i in band)
        r0 = min(tiles[i].row for i in band)
        c1 = max(tiles[i].col + tiles[i].width for i in band)
        r1 = max(tiles[i].row + tiles[i].height for i in band)
        block, _ = m.read(c0, r0, c1 - c0, r1 - r0)
        for i in band:
            t = tiles[i]
            yield np.ascontiguousarray(block[t.row - r0 : t.row - r0 + t.height, t.col - c0 : t.col - c0 + t.width])


__all__ = ["content_hash", "map_reference", "open_checked", "read_windows"]
