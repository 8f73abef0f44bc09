"""Retrieval stage: global descriptor of each query -> Faiss search -> top-N tile ids with scores.

Query-side rotation search (``rotations`` k > 1): the descriptors of the map's tiles are upright, a query of
unknown heading is not. The query is described at k headings (360/k steps), the k descriptors are searched in
one batch and each tile keeps its best score, so the right heading wins without rebuilding the database; the
cost is k descriptors per query. Rotations by multiples of 90 degrees are exact (``np.rot90``); others rotate
about the centre on the same canvas, with the corners left pure black, which DenseVLAD methods mask out.

A heading prior (``heading_deg``, clockwise from north, known within ``heading_tol_deg``) turns the query upright
before it is described (:func:`prior_views`): by the nearest quarter turn (exact) when the heading lies within
20° of one, else by the heading itself on a canvas that holds the whole query (corners mirrored), shrunk like
any query; one descriptor, as upright. Top-5 / top-20 recall of the true tile (rough ±15° headings; exact in
brackets), described upright -> turned: NAIP dev-rotated 0.20 / 0.55 -> 0.60 / 0.90 (0.60 / 0.90), levir-tx/any
0.40 / 0.60 -> 0.75 / 0.88 (0.75 / 0.93), szada-hu/any 0.53 / 0.78 -> 0.81 / 0.94 (0.89 / 0.97). Both views
merged did no better (levir-tx/any rough 0.63 / 0.90, szada-hu/any 0.78 / 0.94) at up to 3x the descriptor
time (the turned canvas has up to twice the pixels); black corners instead of mirrored lost NAIP dev-rotated
0.875 -> 0.80 at top 20; the turned view shrunk to the query's own pixel count lost 0.90 -> 0.875.

Turned tiles (``aeroloc build --global-turns``): every tile also described at the seven other turns, so a photo
of unknown heading (``turned``) searches them with its one upright descriptor. The upright top-N is interleaved
with the best ``TURNED_LEAD`` of the ranking by each tile's best turn (upright 1st, turned 1st, upright 2nd,
...), the rest of the turned top-N behind it: a north-up photo keeps its upright top-1 first and its upright
order (over all 8 x N entries the turned views of other places outscore its true tile: levir-tx/north recall@3
0.95 -> 0.63 by the turned ranking alone), a turned photo gets its turned ranking's best near the front
(levir-tx/any recall@3 0.55 -> 0.73, szada-hu/any 0.56 -> 0.92 by the turned ranking).

Query scale: tiles are cut to about a query's footprint (that is how zoom is chosen), so a query much larger in
pixels than a tile is finer than the map. It is shrunk to ``query_scale`` x the tile side first (default 1.5).
Measured with effnet-vlad: Toledo's 1200 px drone photos against 400 px tiles, VPR R@1/3 0.51/0.61 unshrunk,
0.54/0.77 at 1.5, 0.58/0.88 at 1.0, descriptor 560 -> 150 -> 80 ms; NAIP queries, which already have the
map's ground resolution, lose at 1.0 (R@1 0.725 -> 0.667 on 1000 m tiles) and are untouched at 1.5.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from itertools import zip_longest

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.frames import TILE_TURNS, inverse_turn
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.descriptors import describe_image
from aeroloc.retrieval.index import search

QUERY_SCALE = 1.5  # longest query side, in tile sides (see the module docstring)
# the turned ranking's best few interleaved with the upright top-N (the rest behind it): its recall@5 on the
# photos of unknown heading (levir-tx/any 0.83, szada-hu/any 0.97, NAIP dev-rotated 0.70) is most of its
# recall@20 (0.95, 1.00, 0.98). Interleaving all of it pushed a weak frame's true tile back: the first frame
# after a NAIP flight's outage, true tile at upright rank 16, went to rank 26, behind a tile the turned ranking
# put 9th, which took its place among the weak screens re-tried at their own angle; the frame was not placed
# and the track took 51 frames to recover instead of 4 (telemetry flight, seed 4; no-metadata seed 2: 4 -> 7)
TURNED_LEAD = 5


@dataclass
class Retrieval:
    tile_ids: list[str]
    scores: list[float]
    times_ms: dict = field(default_factory=dict)  # descriptor, search
    # tile id -> {rotation index: score}: the query's similarity to the tile at each turn the turned search
    # found it at (:meth:`Retriever.fuse_turned`; rotation indices as the re-ranker turns the query), else None
    turn_scores: dict[str, dict[int, float]] | None = None


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


PRIOR_TURN_TOL_DEG = 30.0  # a heading known this well gives one view; looser: also the quarter turns it reaches
QUARTER_TURN_DEG = 20.0  # a heading this close to a quarter turn is described at that turn (exact, no canvas)


def prior_views(image: np.ndarray, heading_deg: float, heading_tol_deg: float) -> list[np.ndarray]:
    """The query turned upright by a heading prior (see the module docstring): by the nearest quarter turn when
    the heading is within ``QUARTER_TURN_DEG`` of it, else by the heading itself (mirrored corners); a tolerance
    beyond ``PRIOR_TURN_TOL_DEG`` adds every other quarter turn within the tolerance + 45° of the heading (the
    VLAD bridges the rest), at most 5 views. The heading is clockwise from north: turning the image
    counter-clockwise by it brings north up (as the re-ranker's ``turn_deg``)."""
    from aeroloc.core.frames import turned

    def off(a: float) -> float:
        return abs((a - heading_deg + 180.0) % 360.0 - 180.0)

    quarters = sorted(range(4), key=lambda k: off(90.0 * k))
    near = off(90.0 * quarters[0]) <= QUARTER_TURN_DEG
    views = [np.ascontiguousarray(np.rot90(image, quarters[0]))] if near else [turned(image, heading_deg, "mirror")[0]]
    if heading_tol_deg > PRIOR_TURN_TOL_DEG:
        ks = [k for k in quarters[1 if near else 0 :] if off(90.0 * k) <= heading_tol_deg + 45.0]
        views += [np.ascontiguousarray(np.rot90(image, k)) for k in ks]
    return views


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
        self._turned_index = False  # not loaded yet (None: the database has no turned descriptors)
        self.device = device

    def shrink(self, image: np.ndarray) -> np.ndarray:
        """The query at most ``max_query_side`` pixels on its longer side (area-averaged)."""
        from aeroloc.core.frames import fit_within

        return fit_within(image, self.max_query_side)

    def describe(
        self,
        image: np.ndarray,
        rotations: int | None = None,
        heading: tuple[float, float] | None = None,
        mirror: bool = False,
    ) -> tuple[np.ndarray, float]:
        """(k x dim descriptors of the query at its k headings, ms); shrinking and turning included. ``heading``
        (degrees clockwise from north, tolerance) describes the views of :func:`prior_views` instead of
        ``rotations``; a tolerance of 180° or more is no heading. ``mirror``: the k headings that are not
        quarter turns are turned on a canvas that holds the whole query, corners mirrored (as a heading prior's
        view), not cut to the query's own canvas with black corners."""
        k = self.rotations if rotations is None else check_rotations(rotations)
        t0 = time.perf_counter()
        image = self.shrink(image)
        if heading is not None and heading[1] < 180.0:  # a turned canvas is shrunk again, like any query
            views = [self.shrink(v) for v in prior_views(image, *heading)]
        elif mirror and k > 1:
            views = [self.shrink(prior_views(image, 360.0 * i / k, 0.0)[0]) for i in range(k)]
        elif k == 1:
            views = [image]
        else:
            views = list(rotated_views(image, k))
        t_desc = (time.perf_counter() - t0) * 1000  # the total over the views, turning the image included
        descs = []
        for view in views:
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

    @property
    def turned_index(self):
        """The index of the tiles at the seven other turns (:meth:`Database.load_turned`), or None."""
        if self._turned_index is False:
            self._turned_index = self.db.load_turned(self.method)
        return self._turned_index

    def fuse_turned(self, desc: np.ndarray, upright: Retrieval, top_n: int, cut: bool = True) -> Retrieval:
        """``upright`` (the top-N of the 1 x dim ``desc``) interleaved with the top-N by each tile's best score
        over its eight turns (see the module docstring), without repeats; cut at N, or (``cut`` False) the whole
        union, so that every tile of the upright top-N is still there; each tile's score is its best. The
        turned index's top 7N rows hold the 7 turns' top-N tiles (a tile has 7 rows), and a tile's best over
        the upright and the turned lists is exact for the merged top-N, as in :meth:`rank`."""
        t0 = time.perf_counter()
        n_turns = len(TILE_TURNS)
        scores, rows = search(self.turned_index, desc, top_n * n_turns)
        pos = self.db.position
        upright_pos = [pos[t] for t in upright.tile_ids]
        best = dict(zip(upright_pos, upright.scores))
        by_turn: dict[int, dict[int, float]] = {j: {0: v} for j, v in best.items()}
        for r, v in zip(rows[0].tolist(), scores[0].tolist()):
            if r < 0:
                continue
            # the upright query against the tile turned by TILE_TURNS[i] is the query turned back against the tile
            by_turn.setdefault(r // n_turns, {}).setdefault(inverse_turn(TILE_TURNS[r % n_turns]), v)
            if v > best.get(r // n_turns, -np.inf):
                best[r // n_turns] = v
        by_turns = sorted(best, key=lambda j: (-best[j], j))[:top_n]
        lead = by_turns[:TURNED_LEAD]
        fused = list(dict.fromkeys(j for pair in zip_longest(upright_pos, lead) for j in pair if j is not None))
        fused = list(dict.fromkeys(fused + by_turns))
        fused = fused[:top_n] if cut else fused
        ms = upright.times_ms.get("search", 0.0) + (time.perf_counter() - t0) * 1000
        ids = [self.db.tiles[j].id for j in fused]
        turns = {t: by_turn[j] for t, j in zip(ids, fused)}
        return Retrieval(ids, [float(best[j]) for j in fused], {"search": ms}, turns)

    def __call__(
        self,
        image: np.ndarray,
        top_n: int,
        rotations: int | None = None,
        heading: tuple[float, float] | None = None,
        mirror: bool = False,
        turned: bool = False,
    ) -> Retrieval:
        """Top-N tiles for one query; ``heading`` (degrees clockwise from north, tolerance) and ``mirror`` as in
        :meth:`describe`. ``turned`` (a photo of unknown heading, described upright): fused with the database's
        turned tiles when it has them, the union of both top-N lists (:meth:`fuse_turned`; up to 2N tiles): the
        turned tiles add candidates and move a few forward, they never drop one of the upright top-N."""
        desc, t_desc = self.describe(image, rotations, heading, mirror)
        r = self.rank([desc], top_n)[0]
        if turned and len(desc) == 1 and self.turned_index is not None:
            r = self.fuse_turned(desc, r, top_n, cut=False)
        r.times_ms = {"descriptor": t_desc, **r.times_ms}
        return r
