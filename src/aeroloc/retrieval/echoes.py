"""Ground the map shows twice: a mosaic of overlapping scenes (szada-hu's scenes 0 and 1 show one 500 m strip
of forest twice, 554 m apart) holds places no localizer can tell apart, so a fix there must be checked at the
other copy too (aeroloc.localization.localizer.Localizer._echo_rival).

Found at build time, scalably: each tile's nearest tiles by global descriptor (the index the database already
has), farther than a tile side from it, are correlated with it (normalised cross-correlation of the grey tile,
shrunk to at most 96 px, over the other tile's window grown by half a tile); a peak of at least ``min_score`` is
an *echo*: the tile's ground again at an offset. Look-alike texture (suburban streets, fields) peaks at 0.4-0.8
over small patches but a whole tile's echo stays below 0.7 on every shared map except szada-hu's strip (0.8-0.96;
``benchmarks/repeated_ground.py`` measures the maps patch by patch).

Stored as ``echoes.json`` in the database (tile id, offset in map px, score), keyed by the tiles' identity and the
descriptor method that proposed the pairs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ECHOES_JSON = "echoes.json"
MIN_SCORE = 0.7
NEIGHBOURS = 3
WORK_PX = 96  # the correlated tile's side after shrinking


@dataclass(frozen=True)
class Echo:
    tile_id: str
    dx: int  # map px from the tile to its echo
    dy: int
    score: float


def _grey(rgb: np.ndarray, shrink: float) -> np.ndarray:
    import cv2

    g = rgb.astype(np.float32).mean(2)
    if shrink > 1:
        g = cv2.resize(g, (max(1, round(g.shape[1] / shrink)), max(1, round(g.shape[0] / shrink))), cv2.INTER_AREA)
    return g


def _echo_of(db, m, a, b, shrink: float, min_score: float) -> Echo | None:
    """Tile ``a`` correlated over tile ``b``'s window grown by half a tile: its echo there, or None."""
    import cv2

    ta = _grey(db.tile_image(a.id), shrink)
    if ta.std() < 4.0:  # water, haze, no data: correlation means nothing
        return None
    gx, gy = a.width // 2, a.height // 2
    c0, r0 = max(0, b.col - gx), max(0, b.row - gy)
    c1, r1 = min(m.width, b.col + b.width + gx), min(m.height, b.row + b.height + gy)
    if c1 - c0 < a.width or r1 - r0 < a.height:
        return None
    rgb, valid = m.read(c0, r0, c1 - c0, r1 - r0)
    wb = _grey(rgb, shrink)
    vb = _grey(valid[..., None].astype(np.float32) * 255, shrink) > 254
    if wb.shape[0] < ta.shape[0] or wb.shape[1] < ta.shape[1]:
        return None
    res = cv2.matchTemplate(wb, ta, cv2.TM_CCOEFF_NORMED)
    h, w = ta.shape
    ok = cv2.erode(vb.astype(np.uint8), np.ones((h, w), np.uint8), anchor=(0, 0))[: res.shape[0], : res.shape[1]]
    res = np.where(ok > 0, res, -1.0)
    k = int(res.argmax())
    score = float(res.flat[k])
    if not math.isfinite(score) or score < min_score:
        return None
    y, x = divmod(k, res.shape[1])
    dx, dy = round(c0 + x * shrink) - a.col, round(r0 + y * shrink) - a.row
    if math.hypot(dx, dy) < max(a.width, a.height):  # the tile itself or an overlapping neighbour
        return None
    return Echo(a.id, dx, dy, score)


def find_echoes(db, method: str | None = None, min_score: float = MIN_SCORE, k: int = NEIGHBOURS) -> list[Echo]:
    """Every tile's echoes (see the module doc), at most one per proposed neighbour."""
    from aeroloc.retrieval.index import search

    m = db.source.map()  # the map the tiles were cut from (checked unchanged)
    store, index = db.load_search(method)  # the stored descriptors and their index: no model is needed
    descs = np.asarray(store.load(), np.float32)
    sims, nn = search(index, descs, min(len(db.tiles), k + 8))
    far = []  # per tile, its neighbours farther than a tile side: (similarity, tile)
    for i, a in enumerate(db.tiles):
        side = max(a.width, a.height)
        far.append(
            [
                (float(s), db.tiles[int(j)])
                for s, j in zip(sims[i], nn[i])
                if j >= 0 and math.hypot(db.tiles[int(j)].col - a.col, db.tiles[int(j)].row - a.row) >= side
            ][:k]
        )
    # only pairs well above what a far tile typically scores are correlated (the cost; the correlation decides):
    # szada-hu's doubled tiles score 0.25-0.32 against a median first far neighbour of 0.07 (levir-tx: at most 0.17)
    firsts = [f[0][0] for f in far if f]
    floor = 2.0 * float(np.median(firsts)) if firsts else math.inf
    out: list[Echo] = []
    for a, pairs in zip(db.tiles, far):
        shrink = max(1.0, max(a.width, a.height) / WORK_PX)
        for sim, b in pairs:
            if sim < floor:
                break
            e = _echo_of(db, m, a, b, shrink, min_score)
            if e is not None and all(
                math.hypot(e.dx - o.dx, e.dy - o.dy) > a.width / 4 for o in out if o.tile_id == a.id
            ):
                out.append(e)
    return out


def _key(db, method: str | None) -> dict:
    return {"tiles": db.tiles_hash(), "method": method or db.meta.get("default_method"), "min_score": MIN_SCORE}


def build_echoes(db, method: str | None = None) -> list[Echo]:
    """:func:`find_echoes`, written to the database (kept when its key is unchanged)."""
    from aeroloc.core.io import write_json_atomic

    have = load_echoes(db, method)
    if have is not None:
        return have
    echoes = find_echoes(db, method)
    write_json_atomic(
        Path(db.folder) / ECHOES_JSON,
        {"key": _key(db, method), "echoes": [[e.tile_id, e.dx, e.dy, round(e.score, 4)] for e in echoes]},
    )
    return echoes


def load_echoes(db, method: str | None = None) -> list[Echo] | None:
    """The stored echoes, or None when they were never found for these tiles (``aeroloc build`` finds them)."""
    import json

    p = Path(db.folder) / ECHOES_JSON
    if not p.is_file():
        return None
    data = json.loads(p.read_text())
    if data.get("key") != _key(db, method):
        return None
    return [Echo(t, int(dx), int(dy), float(s)) for t, dx, dy, s in data["echoes"]]


def same_ground(m, corners: np.ndarray, dx: int, dy: int, search_px: int = 4) -> float | None:
    """How alike the map is under the polygon ``corners`` (map px) and under it shifted by (``dx``, ``dy``):
    the best masked correlation within ``search_px`` of the offset (an echo's offset is found on shrunk tiles);
    None when either copy leaves the map or the footprint shows no texture."""
    import cv2

    (x0, y0), (x1, y1) = np.floor(corners.min(0)).astype(int), np.ceil(corners.max(0)).astype(int)
    g = search_px
    if x0 < 0 or y0 < 0 or x1 > m.width or y1 > m.height or x1 - x0 < 8 or y1 - y0 < 8:
        return None
    bx0, by0, bx1, by1 = x0 + dx - g, y0 + dy - g, x1 + dx + g, y1 + dy + g
    if bx0 < 0 or by0 < 0 or bx1 > m.width or by1 > m.height:
        return None
    rgb, va = m.read(x0, y0, x1 - x0, y1 - y0)
    a = rgb.astype(np.float32).mean(2)
    mask = np.zeros(a.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(corners - [x0, y0]).astype(np.int32)], 1)
    mask &= va.astype(np.uint8)
    rgb, vb = m.read(bx0, by0, bx1 - bx0, by1 - by0)
    b = rgb.astype(np.float32).mean(2)
    sel = mask > 0
    if sel.sum() < 64:
        return None
    av = a[sel] - a[sel].mean()
    na = float(np.sqrt((av * av).sum()))
    if na / np.sqrt(sel.sum()) < 4.0:  # no texture: water, haze
        return None
    best = -1.0
    h, w = a.shape
    for sy in range(2 * g + 1):
        for sx in range(2 * g + 1):
            if not vb[sy : sy + h, sx : sx + w][sel].all():
                continue
            bv = b[sy : sy + h, sx : sx + w][sel]
            bv = bv - bv.mean()
            nb = float(np.sqrt((bv * bv).sum()))
            if nb > 0:
                best = max(best, float((av * bv).sum()) / (na * nb))
    return best if best > -1.0 else None
