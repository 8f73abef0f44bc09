"""The query-time pipeline: retrieve top-N -> re-rank to top-K by verified inliers -> align -> lat/lon.

``localize_queries`` streams one CSV row per query to ``OUT.part`` as it goes, so an interrupted run resumes
where it stopped (same configuration) and nothing finished is lost; the final file appears by rename.
"""

from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.images import read_image
from aeroloc.localization.alignment import Alignment, align
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.retriever import QUERY_SCALE, Retriever, check_rotations

STAGES = ("descriptor", "search", "local_features", "rerank", "align")
COLUMNS = [
    "name",
    "lat",
    "lon",
    "status",
    "inliers",
    "top_tiles",
    "retrieved_tiles",
    *(f"{s}_ms" for s in STAGES),
    "total_ms",
]


@dataclass
class Localization:
    name: str
    lat: float = float("nan")
    lon: float = float("nan")
    status: str = ""
    inliers: int = 0
    top_tiles: list[str] = field(default_factory=list)
    retrieved: list[str] = field(default_factory=list)
    times_ms: dict = field(default_factory=dict)
    best = None  # rerank.Candidate, for visualisation
    dense = None  # densemap.DenseResult, for visualisation

    def row(self) -> dict:
        """The results-CSV row, all strings: a fresh, resumed or cached run returns equal rows."""
        loc = np.isfinite(self.lat)
        r = {
            "name": self.name,
            "lat": f"{self.lat:.8f}" if loc else "",
            "lon": f"{self.lon:.8f}" if loc else "",
            "status": self.status,
            "inliers": str(self.inliers),
            "top_tiles": ";".join(self.top_tiles),
            "retrieved_tiles": ";".join(self.retrieved),
        }
        for s in STAGES:
            r[f"{s}_ms"] = f"{self.times_ms.get(s, 0.0):.2f}"
        r["total_ms"] = f"{sum(self.times_ms.get(s, 0.0) for s in STAGES):.2f}"
        return r


class Localizer:
    def __init__(
        self,
        db: Database,
        method: str | None = None,
        rerank: str | None = "xfeat-lighterglue",
        device="cpu",
        rerank_conf: dict | None = None,
        rotations: int = 1,
        query_gsd: float | None = None,
        dense_conf: dict | None = None,
    ):
        from aeroloc.localization.cascade import Reranker
        from aeroloc.localization.dense_stage import check_query_gsd

        self.db = db
        self.retriever = Retriever(db, method, device, rotations)  # rotations: query headings searched
        self.reranker = Reranker(db, rerank, device, rerank_conf) if rerank else None
        m = db.info["map"]
        self.map_size = (int(m["width"]), int(m["height"]))
        self.query_gsd = check_query_gsd(query_gsd)  # metres per query pixel: turns the dense stage on
        self.dense_conf = (
            dense_conf  # aeroloc.matching.dense settings (default headings ±15°: see dense.heading_angles)
        )

    def __call__(self, name: str, image: np.ndarray, top_n: int = 20, top_k: int = 1) -> Localization:
        from aeroloc.core.device import single_threaded_blas

        with single_threaded_blas():
            return self._localize(name, image, top_n, top_k)

    def _localize(self, name: str, image: np.ndarray, top_n: int, top_k: int) -> Localization:
        r = self.retriever(image, top_n)
        out = Localization(name, retrieved=r.tile_ids, times_ms=dict(r.times_ms))
        dense_ms = 0.0
        if self.dense is not None:
            t0 = time.perf_counter()
            d = self.dense.locate(image, [self.db.by_id[t] for t in r.tile_ids])
            dense_ms = (time.perf_counter() - t0) * 1000
            if d is not None:
                out.times_ms["align"] = dense_ms
                out.lat, out.lon, out.status, out.dense = d.lat, d.lon, d.status(), d
                out.top_tiles = self._tiles_around(d.col, d.row, r.tile_ids)[: top_k or None]
                return out
        if self.reranker is None:  # retrieval only: best tile centre, no alignment
            out.top_tiles = r.tile_ids[:top_k] if top_k else r.tile_ids
            out.lat, out.lon = self.db.by_id[r.tile_ids[0]].centre_latlon
            out.status = "retrieval only"
            return out
        rr = self.reranker(image, r.tile_ids, top_k)
        out.times_ms.update(rr.times_ms)
        out.top_tiles = [c.tile_id for c in rr.candidates]
        best = rr.candidates[0]
        out.best = best
        t0 = time.perf_counter()
        conf = self.reranker.conf
        a = align(
            best.H,
            best.score,
            (image.shape[1], image.shape[0]),
            self.db.by_id[best.tile_id],
            self.map_size,
            conf["min_inliers"],
        )
        doubt = self.reranker.doubt(best) if a.localized else None
        if doubt:
            a = Alignment(f"not localized: {doubt}")
        if self._should_realign(a, best, (image.shape[1], image.shape[0])):
            a = self._realign(image, best, rr.query.get(best.rot_k)) or a
        out.times_ms["align"] = (time.perf_counter() - t0) * 1000 + dense_ms
        out.lat, out.lon, out.status, out.inliers = a.lat, a.lon, a.status, best.score
        return out

    def _should_realign(self, a: Alignment, best, query_size) -> bool:
        from aeroloc.localization.window import beyond_tile

        conf = self.reranker.conf
        if best.H is None:
            return False
        if not a.localized:
            return conf["refine_min"] is not None and conf["refine_min"] <= best.score < conf["min_inliers"]
        return (
            conf["refine_outside"] is not None
            and beyond_tile(best.H, query_size, self.db.by_id[best.tile_id]) > conf["refine_outside"]
        )

    def _realign(self, image: np.ndarray, best, qf) -> Alignment | None:
        """The best match re-matched against the map window its transform says the query covers (aeroloc.localization.window):
        the window's alignment when it passes with more inliers than the tile had (``best`` then takes the
        window's inliers and transform), else None."""
        from aeroloc.localization.window import query_window

        tile = self.db.by_id[best.tile_id]
        if qf is None or self.map is None:
            return None
        window = query_window(self.map, tile, best.H, (image.shape[1], image.shape[0]))
        if window is None:
            return None
        n, H, n_matches, _vis = self.reranker.match_window(qf, window, tile)
        a = align(H, n, (image.shape[1], image.shape[0]), window.tile, self.map_size, self.reranker.conf["min_inliers"])
        if not a.localized or n <= best.score:
            return None
        best.inliers, best.H, best.n_matches, best.matches = n, H, n_matches, None
        return a

    def _tiles_around(self, col: float, row: float, retrieved: list[str]) -> list[str]:
        """The re-ranked list for a dense position: every tile containing it (nearest centre first, retrieved or
        not), then the other retrieved tiles in retrieval order."""
        inside = sorted(
            (t for t in self.db.tiles if t.col <= col <= t.col + t.width and t.row <= row <= t.row + t.height),
            key=lambda t: (t.col + t.width / 2 - col) ** 2 + (t.row + t.height / 2 - row) ** 2,
        )
        ids = [t.id for t in inside]
        taken = set(ids)
        return ids + [t for t in retrieved if t not in taken]

    @cached_property
    def dense(self):
        """The dense structural stage (aeroloc.localization.dense_stage) when the queries' ground resolution is known, else None;
        also None (with a warning) when the map can't be opened."""
        from aeroloc.localization.dense_stage import DenseMapLocator

        if self.query_gsd is None or self.map is None:
            return None
        return DenseMapLocator(self.map, self.query_gsd, self.dense_conf)

    @cached_property
    def map(self):
        """The database's map, opened on first use; None (with a warning) when it can't be opened any more."""
        from aeroloc.localization.window import open_map_for_refine

        return open_map_for_refine(self.db.info["map"]["path"])


def heading_conf(rerank_conf: dict | None, north_up: bool, rotations: int) -> dict | None:
    """The re-ranker overrides for queries known to be north-up (within about ±45°, e.g. from a compass or
    gimbal yaw, or satellite imagery): no 90° rotation search, so one query extraction and no screens at wrong
    headings."""
    if not north_up:
        return rerank_conf
    if rotations != 1:
        raise AerolocError(
            f"--north-up and --rotations > 1 contradict each other: north-up queries need no rotation "
            f"search, but rotations={rotations} was asked for"
        )
    return {**(rerank_conf or {}), "rotations": [0]}


def _config_signature(**kw) -> str:
    return json.dumps(kw, sort_keys=True, default=str)


def localize_queries(
    db: Database,
    queries,
    out_csv,
    top_n=20,
    top_k=1,
    method=None,
    rerank="xfeat-lighterglue",
    device="cpu",
    rerank_conf=None,
    save_matches=None,
    progress=True,
    rotations=1,
    north_up=False,
    query_gsd=None,
    dense_conf=None,
) -> list[dict]:
    """Localize every query, streaming rows to ``out_csv`` (resumable). Returns the rows.

    ``rotations`` > 1 retrieves with the query at that many headings; ``north_up`` skips the re-ranker's 90°
    rotation search (see :func:`heading_conf`); ``query_gsd`` (metres per query pixel) first tries the dense
    structural stage (aeroloc.matching.dense: headings around north when ``north_up``, else all), local features only when
    it finds no distinct match."""
    from tqdm import tqdm

    from aeroloc.localization.dense_stage import check_query_gsd
    from aeroloc.matching.dense import heading_angles

    rotations = check_rotations(rotations)  # before any file is touched
    query_gsd = check_query_gsd(query_gsd)
    dense_conf = heading_angles(dense_conf, north_up) if query_gsd is not None else None
    rerank_conf = heading_conf(rerank_conf, north_up, rotations)
    out_csv = Path(out_csv)
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    part = out_csv.with_name(out_csv.name + ".part")
    sig_path = out_csv.with_name(out_csv.name + ".config")
    from aeroloc.matching.registry import rerank_conf as full_conf

    sig = _config_signature(
        db=str(db.folder.resolve()),
        top_n=top_n,
        top_k=top_k,
        method=method,
        rerank=rerank,
        rerank_conf=full_conf(rerank, rerank_conf) if rerank else None,
        global_=db.meta.get("global", {}).get(method or db.meta.get("default_method")),
        queries=[q.name for q in queries],
        query_scale=QUERY_SCALE,
        # rotations only when searched, so the signature of an upright run stays as it was
        **({"rotations": rotations} if rotations != 1 else {}),
        **({"query_gsd": query_gsd, "dense": dense_conf} if query_gsd is not None else {}),
    )
    done_sig = out_csv.with_name(out_csv.name + ".done")
    if out_csv.is_file() and done_sig.is_file() and done_sig.read_text() == sig:
        with open(out_csv, newline="") as f:
            return list(csv.DictReader(f))  # same configuration finished before: cached
    done_sig.unlink(missing_ok=True)
    rows = []
    if part.is_file() and sig_path.is_file() and sig_path.read_text() == sig:
        with open(part, newline="") as f:
            rows = list(csv.DictReader(f))
    done = {r["name"] for r in rows}
    sig_path.write_text(sig)
    localizer = Localizer(db, method, rerank, device, rerank_conf, rotations, query_gsd, dense_conf)
    new_file = not part.is_file() or not rows
    with open(part, "w" if new_file else "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        if new_file:
            w.writeheader()
        todo = [q for q in queries if q.name not in done]
        bar = tqdm(todo, desc="localize", unit="query", disable=not progress, leave=False, dynamic_ncols=True)
        for q in bar:
            try:
                image = read_image(q.path)
            except AerolocError as exc:
                res = Localization(q.name, status=f"not localized: {exc}")
            else:
                res = localizer(q.name, image, top_n, top_k)
                if save_matches and res.best is not None:
                    save_match_image(Path(save_matches) / f"{Path(q.name).stem}.jpg", image, db, res)
                elif save_matches and res.dense is not None:
                    save_dense_image(Path(save_matches) / f"{Path(q.name).stem}.jpg", image, localizer.dense, res)
            row = res.row()
            w.writerow(row)
            f.flush()
            rows.append(row)
    os.replace(part, out_csv)
    done_sig.write_text(sig)
    sig_path.unlink(missing_ok=True)
    return rows


def save_dense_image(path: Path, image: np.ndarray, dense, res: Localization) -> None:
    """Query | the map around its dense position (both 480 px high), the query's footprint outlined in green."""
    import cv2

    from aeroloc.core.images import write_image

    m = dense.map
    xy = res.dense.footprint((image.shape[1], image.shape[0]), dense.query_gsd, dense.map_gsd)
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


def save_match_image(path: Path, image: np.ndarray, db: Database, res: Localization) -> None:
    """Query | best tile side by side (both scaled to 480 px high), inlier matches in green, outliers red."""
    import cv2

    from aeroloc.core.images import write_image

    c = res.best
    tile = read_image(db.folder / db.by_id[c.tile_id].path)
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
