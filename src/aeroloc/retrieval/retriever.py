"""Retrieval stage: global descriptor of each query -> Faiss search -> top-N tile ids with scores.

Query-side rotation search (``rotations`` k > 1): the descriptors of the map's tiles are upright, a query of
unknown heading is not. The query is described at k headings (360/k steps), the k descriptors are searched in
one batch and each tile keeps its best score, so the right heading wins without rebuilding the database; the
cost is k descriptors per query. Rotations by multiples of 90 degrees are exact (``np.rot90``); others rotate
about the centre on the same canvas, with the corners left pure black, which DenseVLAD methods mask out.

Query scale: tiles are cut to about a query's footprint (that is how zoom is chosen), so a query much larger in
pixels than a tile is finer than the map. It is shrunk to ``query_scale`` x the tile side first (default 1.5).
Measured with effnet-vlad: Toledo's 1200 px drone photos against 400 px tiles, VPR R@1/3 0.51/0.61 unshrunk,
0.54/0.77 at 1.5, 0.58/0.88 at 1.0, descriptor 560 -> 150 -> 80 ms; NAIP queries, which already have the
map's ground resolution, lose at 1.0 (R@1 0.725 -> 0.667 on 1000 m tiles) and are untouched at 1.5.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.descriptors import describe_image
from aeroloc.retrieval.index import search

QUERY_SCALE = 1.5  # longest query side, in tile sides (see the module docstring)


@dataclass
class Retrieval:
    tile_ids: list[str]
    scores: list[float]
    times_ms: dict = field(default_factory=dict)  # descriptor, search


def check_rotations(rotations) -> int:
    if isinstance(rotations, bool) or not isinstance(rotations, (int, np.integer)) or rotations < 1:
        raise AerolocError(f"rotations must be an integer >= 1 (1 = upright query only), got {rotations!r}")
    return int(rotations)


def rotated_views(image: np.ndarray, k: int):
    """The image turned counter-clockwise by 360 * i / k degrees, i = 0 .. k-1."""
    for i in range(k):
        angle = 360.0 * i / k
        if angle % 90 == 0:
            yield np.ascontiguousarray(np.rot90(image, int(angle // 90)))
        else:
            yield rotate_image(image, angle)


def rotate_image(image: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotate counter-clockwise about the centre, same size; every pixel not fully inside the source is set to
    pure black (interpolated border pixels would otherwise be dark but valid for the VLAD's no-data mask)."""
    import cv2

    h, w = image.shape[:2]
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), angle_deg, 1.0)
    out = cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = cv2.warpAffine(
        np.ones((h, w), np.float32), m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    out[inside < 0.99] = 0
    return out


class Retriever:
    """Holds a database's method, descriptors and index; ``__call__(image)`` retrieves top-N tiles.

    ``rotations`` (default for every call, or per call) > 1 searches the query at that many headings.
    """

    def __init__(
        self,
        db: Database,
        method: str | None = None,
        device="cpu",
        rotations: int = 1,
        query_scale: float | None = QUERY_SCALE,
    ):
        self.rotations = check_rotations(rotations)
        if query_scale is not None and not query_scale > 0:
            raise AerolocError(f"query_scale must be > 0 (or None: keep the query's size), got {query_scale!r}")
        self.db = db
        self.max_query_side = query_scale * max(max(t.width, t.height) for t in db.tiles) if query_scale else None
        self.model, self.store, self.index, self.entry = db.load_method(method, device)
        self.method = method or db.meta.get("default_method")
        self.device = device

    def shrink(self, image: np.ndarray) -> np.ndarray:
        """The query at most ``max_query_side`` pixels on its longer side (area-averaged)."""
        from aeroloc.core.frames import fit_within

        return fit_within(image, self.max_query_side)

    def describe(self, image: np.ndarray, rotations: int | None = None) -> tuple[np.ndarray, float]:
        """(k x dim descriptors of the query at its k headings, ms); shrinking and turning included."""
        k = self.rotations if rotations is None else check_rotations(rotations)
        t0 = time.perf_counter()
        image = self.shrink(image)
        t_desc = (time.perf_counter() - t0) * 1000
        if k == 1:
            desc, t = describe_image(self.model, image, self.device)
            return desc, t_desc + t
        descs = []  # the total over the k views, turning the image included
        views = rotated_views(image, k)
        for _ in range(k):
            t0 = time.perf_counter()
            view = next(views)
            t_desc += (time.perf_counter() - t0) * 1000
            d, t = describe_image(self.model, view, self.device)
            descs.append(d)
            t_desc += t
        return np.concatenate(descs), t_desc

    def rank(self, descs: list[np.ndarray], top_n: int) -> list[Retrieval]:
        """Top-N tiles of many queries (each a k x dim block from :meth:`describe`) in one Faiss search.

        Exact search over many tiles is memory-bound: one query alone scans every descriptor (10^4 x 8192-d:
        ~26 ms), a batch shares the scan (0.7 ms a query for 200). ``search`` in ``times_ms`` is the batch's
        time divided by its queries. A query's k heading rows merge by each tile's best score; ties by tile order.
        """
        t0 = time.perf_counter()
        scores, ids = search(self.index, np.concatenate(descs), top_n)
        t_search = (time.perf_counter() - t0) * 1000 / max(1, len(descs))
        tiles, out, row = self.db.tiles, [], 0
        for d in descs:
            s, i = scores[row : row + len(d)], ids[row : row + len(d)]
            row += len(d)
            if len(d) == 1:
                keep = i[0] >= 0
                order, best = i[0][keep].tolist(), dict(zip(i[0][keep].tolist(), s[0][keep].tolist()))
            else:
                # each rotation's top-N holds every tile of the merged top-N (a tile's best score is its score in
                # some rotation, and a tile outside that rotation's top-N has N tiles at least as good)
                best: dict[int, float] = {}
                for j, v in zip(i.ravel().tolist(), s.ravel().tolist()):
                    if j >= 0 and v > best.get(j, -np.inf):
                        best[j] = v
                order = sorted(best, key=lambda j: (-best[j], j))[:top_n]
            out.append(Retrieval([tiles[j].id for j in order], [float(best[j]) for j in order], {"search": t_search}))
        return out

    def __call__(self, image: np.ndarray, top_n: int, rotations: int | None = None) -> Retrieval:
        desc, t_desc = self.describe(image, rotations)
        r = self.rank([desc], top_n)[0]
        r.times_ms = {"descriptor": t_desc, **r.times_ms}
        return r
