"""Scores of localization results (:class:`aeroloc.localization.results.Localization`, as ``aeroloc localize``
returns and writes them; :func:`aeroloc.localization.results.read_localizations` reads a results CSV).

- VPR Recall@N: the ground-truth centre lies inside one of the top-N tiles (tested in the map's CRS through
  each tile's exact affine transform, boundaries inclusive).
- distance Recall@N@d: the centre of one of the top-N tiles lies within d metres of the truth (meaningful
  across zooms and overlaps, unlike containment).
- Georeference Recall@d: the estimated position lies within d metres (WGS84 geodesic) of the truth; a query
  not localized (or missing from the results) is a miss.
- error statistics over the localized queries (median, 90th percentile) and the share not localized.
"""

from __future__ import annotations

import math

import numpy as np

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError
from aeroloc.core.queries import Query
from aeroloc.localization.results import Localization
from aeroloc.maps.tiling import Tile

EPS_PX = 1e-6
DEFAULT_NS = (1, 5, 10)
DEFAULT_THRESHOLDS = (10.0, 25.0, 50.0, 100.0)


def tile_contains(tile: Tile, lat: float, lon: float) -> bool:
    x, y = tile.latlon_to_pixel(lat, lon)
    return bool(-EPS_PX <= x <= tile.width + EPS_PX and -EPS_PX <= y <= tile.height + EPS_PX)


def first_hit(top: tuple[str, ...], tiles: dict[str, Tile], lat: float, lon: float) -> int | None:
    """Rank (0-based) of the first listed tile containing the point, or None."""
    for rank, tid in enumerate(top):
        t = tiles.get(tid)
        if t is not None and tile_contains(t, lat, lon):
            return rank
    return None


def evaluate(
    results: list[Localization], queries: list[Query], tiles: list[Tile] | None, thresholds=DEFAULT_THRESHOLDS, ns=None
) -> dict:
    """Metrics as fractions in [0, 1] (keys documented in the module docstring and the README)."""
    truth = [q for q in queries if q.has_truth]
    if not truth:
        raise AerolocError("no query has a ground-truth position: nothing to evaluate")
    by_name = {r.name: r for r in results}
    tile_map = {t.id: t for t in tiles or []}
    max_len = max((len(r.top_tiles) for r in results), default=0)
    if ns is None:
        ns = sorted({n for n in (*DEFAULT_NS, 20, 50, 100) if n <= max(max_len, 10)} | {max_len} - {0})
    centres = {t.id: t.centre_latlon for t in tiles or []}
    hits, errors, dist_rank = [], [], {d: [] for d in thresholds}
    per_query = []
    for q in truth:
        r = by_name.get(q.name) or Localization(q.name)
        hit = first_hit(r.top_tiles, tile_map, q.lat, q.lon) if tile_map else None
        hits.append(hit)
        err = float(geo.geodesic_distance(q.lat, q.lon, r.lat, r.lon)) if r.localized else math.inf
        errors.append(err)
        ids = [t for t in r.top_tiles if t in centres]
        if ids:
            c = np.array([centres[t] for t in ids])
            dists = geo.geodesic_distance(q.lat, q.lon, c[:, 0], c[:, 1])
        else:
            dists = np.array([])
        for d in thresholds:
            within = np.nonzero(dists <= d)[0]
            dist_rank[d].append(int(within[0]) if len(within) else None)
        per_query.append({"name": q.name, "error_m": err, "vpr_rank": hit, "localized": r.localized})
    n = len(truth)
    out: dict = {"n_queries": n}
    if tile_map:
        for k in ns:
            out[f"vpr_recall@{k}"] = sum(h is not None and h < k for h in hits) / n
        for d in thresholds:
            for k in ns:
                out[f"dist_recall@{k}@{_fmt(d)}m"] = sum(h is not None and h < k for h in dist_rank[d]) / n
    errs = np.array(errors)
    for d in thresholds:
        out[f"georef_recall@{_fmt(d)}m"] = float(np.mean(errs <= d))
    finite = errs[np.isfinite(errs)]
    out["median_error_m"] = float(np.median(finite)) if len(finite) else None
    out["p90_error_m"] = float(np.percentile(finite, 90)) if len(finite) else None
    out["not_localized"] = float(np.mean(~np.isfinite(errs)))
    out["missing_results"] = sum(q.name not in by_name for q in truth)
    out["per_query"] = per_query
    return out


def scaled_recall(per_query: list[dict], map_gsd: float) -> dict:
    """Recall and wrong fixes measured in map pixels as well as metres, so one table compares maps of 0.5 and
    5 m/px: ``georef_recall@t`` within t = max(5 m, 2 map px); ``wrong`` = the share of queries localized farther
    than max(25 m, 10 map px) (a confident wrong answer, worse than none); ``t_m``, ``wrong_m`` the distances."""
    t_m, wrong_m = max(5.0, 2.0 * map_gsd), max(25.0, 10.0 * map_gsd)
    errs = np.array([q["error_m"] for q in per_query], np.float64)
    n = max(1, len(errs))
    wrong = np.isfinite(errs) & (errs > wrong_m)
    return {
        "georef_recall@t": float(np.sum(errs <= t_m) / n),
        "wrong": float(np.sum(wrong) / n),
        "wrong_n": int(np.sum(wrong)),
        "t_m": t_m,
        "wrong_m": wrong_m,
    }


def _fmt(d: float) -> str:
    return f"{d:g}"


def format_table(metrics: dict) -> str:
    """A plain-text table of the scalar metrics (per-query rows left out)."""
    lines = []
    for k, v in metrics.items():
        if k == "per_query" or (k.startswith("dist_recall@") and not k.startswith("dist_recall@1@")):
            continue
        val = "n/a" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))
        lines.append(f"{k:<28}{val:>10}")
    return "\n".join(lines)
