"""Pictures of how a query was localized, for people checking results (``--save-matches``): the query beside
its best tile with the inlier matches, or beside the map with its dense footprint."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from aeroloc.core.images import write_image
from aeroloc.localization.results import Localization


def save_result_image(folder, image: np.ndarray, res: Localization, db, dense=None) -> None:
    """``folder/<query stem>.jpg`` for a result that has something to show (a best match or a dense fix)."""
    path = Path(folder) / f"{Path(res.name).stem}.jpg"
    if res.best is not None:
        save_match_image(path, image, db, res)
    elif res.dense is not None and dense is not None:
        save_dense_image(path, image, dense, res)


def save_dense_image(path: Path, image: np.ndarray, dense, res: Localization) -> None:
    """Query | the map around its dense position (both 480 px high), the query's footprint outlined in green."""
    import cv2

    m = dense.map
    xy = res.dense.footprint((image.shape[1], image.shape[0]))  # at the resolution its search assumed
    (x0, y0), (x1, y1) = xy.min(0), xy.max(0)
    pad = 0.5 * max(x1 - x0, y1 - y0)
    c0, r0 = max(0, int(x0 - pad)), max(0, int(y0 - pad))
    c1, r1 = min(m.width, int(np.ceil(x1 + pad))), min(m.height, int(np.ceil(y1 + pad)))
    crop, _ = m.read(c0, r0, c1 - c0, r1 - r0)
    H0 = 480
    sq, sm = H0 / image.shape[0], H0 / crop.shape[0]
    a = cv2.resize(image, (round(image.shape[1] * sq), H0))
    b = cv2.resize(crop, (round(crop.shape[1] * sm), H0)).copy()
    poly = ((xy - [c0, r0]) * sm).round().astype(np.int32)
    cv2.polylines(b, [poly], True, (0, 220, 0), 2, cv2.LINE_AA)
    cv2.line(b, tuple(poly[0]), tuple(poly[1]), (255, 255, 0), 3, cv2.LINE_AA)  # the query's top edge
    canvas = np.concatenate([a, b], 1)
    cv2.putText(
        canvas, f"{res.name}: {res.status}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 0), 2, cv2.LINE_AA
    )
    write_image(path, canvas, quality=85)


def save_match_image(path: Path, image: np.ndarray, db, res: Localization) -> None:
    """Query | best tile side by side (both scaled to 480 px high), inlier matches in green, outliers red."""
    import cv2

    c = res.best
    tile = db.tile_image(c.tile_id)
    H0 = 480
    sq, st = H0 / image.shape[0], H0 / tile.shape[0]
    a = cv2.resize(image, (round(image.shape[1] * sq), H0))
    b = cv2.resize(tile, (round(tile.shape[1] * st), H0))
    canvas = np.concatenate([a, b], 1).copy()
    if c.matches is not None:
        m0, m1, inl = c.matches
        step = max(1, len(m0) // 300)
        for (x0, y0), (x1, y1), ok in list(zip(m0, m1, inl))[::step]:
            p0 = (int(x0 * sq), int(y0 * sq))
            p1 = (int(x1 * st) + a.shape[1], int(y1 * st))
            cv2.line(canvas, p0, p1, (0, 200, 0) if ok else (200, 0, 0), 1, cv2.LINE_AA)
    label = f"{res.name}: {res.status}, {c.score} inliers, tile {c.tile_id}"
    cv2.putText(canvas, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0), 2, cv2.LINE_AA)
    write_image(path, canvas, quality=85)
