"""Tiles as windows of the map: the pixels of a tile database are read from the map when needed, not copied.

A country-size map has ~10^7 tiles; one PNG each is a few hundred GB of copies and a PNG encode per tile. Instead
the database records which map it was cut from (:func:`map_reference`: path, size, CRS, transform and a hash of
the pixels of sample windows) and reads tiles back through the same :class:`~aeroloc.maps.sources.Map`. A run of
tiles (a shard) is read as few large windows (:func:`read_windows`: one per band of tile rows with the same
column span), so each block of the map is decoded once, not once per tile that overlaps it.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import os
import time
from collections.abc import Callable, Iterator, Sequence
from itertools import groupby
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.maps.sources import Map, open_map

# the content hash tiles.json records: xxh3-128 (0.8 ms for the seed map's 7.1 MB of raw tiles here, SHA-1 5.1 ms,
# most of a cold tiling call); grids made before 2026-12-05 record SHA-1 and are checked with it
CONTENT_KEYS = {"content_xxh3": "xxh3", "content_sha1": "sha1"}
CONTENT_KEY = "content_xxh3"
SAMPLE_WINDOWS = 16  # windows hashed into the map reference (cheap: a country map is never read in full to check)
# a file's hash is cached only when it was last changed at least this long before it was read (see _cached)
HASH_CACHE_MIN_AGE_S = 2.0
RASTER_FILES = {".tif", ".tiff"}  # single-file rasters whose pixels come from that one file (a .vrt names others)


def _spread(n: int, k: int) -> list[int]:
    """Up to ``k`` evenly spaced positions of ``0 .. n - 1``, sorted, without repeats (``np.unique`` of the
    same linspace: numpy 2 imports ``numpy.ma`` on the first ``np.unique``, ~30 ms)."""
    return sorted({int(i) for i in np.linspace(0, n - 1, min(k, n)).astype(int)})


def _hasher(algorithm: str):
    """A fresh hash object of ``algorithm`` (a value of ``CONTENT_KEYS``)."""
    if algorithm == "xxh3":
        import xxhash

        return xxhash.xxh3_128()
    if algorithm == "sha1":
        return hashlib.sha1()
    raise AerolocError(f"unknown content hash {algorithm!r} (known: xxh3, sha1)")


def content_hash(m: Map, tiles: Sequence, algorithm: str = "xxh3") -> str:
    """A hash (``algorithm``: xxh3-128, or SHA-1 for grids made before it) of what the grid reads, sampled: the
    decoded pixels of up to ``SAMPLE_WINDOWS`` evenly spaced tiles of a raster (a COG decodes a window in ~1 ms), or the bytes of as many evenly spaced raw tile files of a tile
    folder (decoding 1280 px PNGs to check would cost as much as the whole grid). Cached per file state
    (:func:`_cached`): a map read before and not changed since is not read again."""
    cells = getattr(m, "cells", None)
    if cells is not None:
        files = [cells[k] for k in sorted(cells)]
        files = [files[i] for i in _spread(len(files), SAMPLE_WINDOWS)]

        def digest() -> str:
            h = _hasher(algorithm)
            for f in files:
                h.update(f.read_bytes())
            return h.hexdigest()

        return _cached("files", files, [], digest, algorithm)
    picked = [tiles[i] for i in _spread(len(tiles), SAMPLE_WINDOWS)] if len(tiles) else []

    def pixels() -> str:
        h = _hasher(algorithm)
        for t in picked:
            rgb, _ = m.read(t.col, t.row, t.width, t.height)
            h.update(np.ascontiguousarray(rgb).tobytes())
        return h.hexdigest()

    path = Path(m.path)
    if path.suffix.lower() not in RASTER_FILES:
        return pixels()
    # GDAL's sidecars (map.tif.msk, .aux.xml, .ovr) can change what is read: their states are part of the key
    files = [path, *sorted(path.parent.glob(glob.escape(path.name) + ".*"))]
    windows = [[t.col, t.row, t.width, t.height] for t in picked]
    return _cached("raster-windows", files, windows, pixels, algorithm)


def hash_cache_dir() -> Path:
    """``$AEROLOC_CACHE/map-hashes`` (default ``~/.cache/aeroloc/map-hashes``: the root of
    :func:`aeroloc.core.weights.cache_dir`, spelled out here: importing that module cost the first tiling call
    12 ms)."""
    root = os.environ.get("AEROLOC_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "aeroloc"
    )
    return Path(root) / "map-hashes"


def _file_states(files: Sequence[Path]) -> list[list[int]]:
    """(size, mtime_ns, ctime_ns, inode, device) of each file. Writing a file or renaming another onto it sets
    its ctime to now, and no system call sets a ctime back (``touch``/``os.utime`` set mtime, and ctime to now)."""
    out = []
    for f in files:
        st = os.stat(f)
        out.append([st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev])
    return out


def _cached(kind: str, files: Sequence[Path], extra: list, compute: Callable[[], str], algorithm: str) -> str:
    """``compute()`` (a content hash of ``files``), remembered under the files' paths and states (size,
    mtime, ctime, inode). An entry is stored only when every file's last change (mtime and ctime) was at least
    ``HASH_CACHE_MIN_AGE_S`` before the read began and no state changed during it: a change that lands in the
    same timestamp tick as the read could otherwise leave the state as it was (git's "racily clean" files)."""
    try:
        before = _file_states(files)
    except OSError:
        return compute()  # a missing file: let the read report it
    from aeroloc.core.io import atomic_write_text, config_key

    key = config_key(kind, [str(Path(f).resolve()) for f in files], before, extra)
    entry = hash_cache_dir() / f"{key}.{algorithm}"
    with contextlib.suppress(OSError):
        got = entry.read_text().strip()
        if len(got) == 2 * _hasher(algorithm).digest_size:  # a whole hex digest of this algorithm
            return got
    start_ns = time.time_ns()
    digest = compute()
    settled = start_ns - int(HASH_CACHE_MIN_AGE_S * 1e9)
    if _file_states(files) == before and all(max(s[1], s[2]) < settled for s in before):
        with contextlib.suppress(OSError):  # an unwritable cache only costs the next read
            atomic_write_text(entry, digest)
    return digest


def map_reference(m: Map, tiles: Sequence) -> dict:
    """What tiles.json records about the map so a later read can tell it is the same one."""
    return {
        "path": str(m.path),
        "kind": type(m).__name__,
        "width": m.width,
        "height": m.height,
        "crs": m.crs,
        "transform": list(m.transform)[:6],
        CONTENT_KEY: content_hash(m, tiles),
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
    for key, algorithm in CONTENT_KEYS.items():
        if ref.get(key) and content_hash(m, tiles, algorithm) != ref[key]:
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


def _band_box(tiles: Sequence, band: list[int], pad: int = 0) -> tuple[int, int, int, int]:
    """(c0, r0, c1, r1) map px of the window holding the band's tiles, grown by ``pad`` on every side."""
    c0 = min(tiles[i].col for i in band) - pad
    r0 = min(tiles[i].row for i in band) - pad
    c1 = max(tiles[i].col + tiles[i].width for i in band) + pad
    r1 = max(tiles[i].row + tiles[i].height for i in band) + pad
    return c0, r0, c1, r1


def read_windows(m: Map, tiles: Sequence) -> Iterator[np.ndarray]:
    """RGB uint8 of each tile in order (the same pixels as ``m.read`` of its window), cut from band reads."""
    for band in _bands(tiles):
        c0, r0, c1, r1 = _band_box(tiles, band)
        block, _ = m.read(c0, r0, c1 - c0, r1 - r0)
        for i in band:
            t = tiles[i]
            yield np.ascontiguousarray(block[t.row - r0 : t.row - r0 + t.height, t.col - c0 : t.col - c0 + t.width])


def turned_windows(m: Map, tiles: Sequence, angles: Sequence[float]) -> Iterator[np.ndarray]:
    """Each tile's view at each of ``angles`` (degrees, counter-clockwise, as ``np.rot90``) in order, tile-major:
    the map turned about the tile's centre and cut to the tile's size, i.e. the tile as a camera turned by that
    angle sees it, its corners filled from the map around it (black beyond the map's edge, which descriptors
    treat as no-data). A quarter turn of a square tile inside the map is exactly ``np.rot90`` of the tile. Read
    per band of tiles (:func:`_bands`) with a margin of half the tiles' diagonal."""
    import cv2

    for band in _bands(tiles):
        pad = max(int(np.ceil(np.hypot(tiles[i].width, tiles[i].height) / 2)) for i in band)
        c0, r0, c1, r1 = _band_box(tiles, band, pad)
        block = np.zeros((r1 - r0, c1 - c0, 3), np.uint8)
        rc0, rr0, rc1, rr1 = max(c0, 0), max(r0, 0), min(c1, m.width), min(r1, m.height)
        block[rr0 - r0 : rr1 - r0, rc0 - c0 : rc1 - c0] = m.read(rc0, rr0, rc1 - rc0, rr1 - rr0)[0]
        for i in band:
            t = tiles[i]
            centre = (t.col - c0 + (t.width - 1) / 2.0, t.row - r0 + (t.height - 1) / 2.0)  # pixel-centre coords
            for a in angles:
                M = cv2.getRotationMatrix2D(centre, float(a), 1.0)
                M[:, 2] -= (t.col - c0, t.row - r0)  # block -> the tile's own frame
                yield cv2.warpAffine(block, M, (t.width, t.height), flags=cv2.INTER_LINEAR)


__all__ = ["content_hash", "hash_cache_dir", "map_reference", "open_checked", "read_windows", "turned_windows"]
