"""The one form of a localization result: :class:`Localization`, and its results-CSV row.

Everything downstream takes these objects: the CLI writes them, the metrics score them, the benchmark tabulates
them. A results CSV (``name,lat,lon,status,inliers,top_tiles,retrieved_tiles,<stage>_ms,total_ms``) reads back
into the same objects (:func:`read_localizations`), with the timings, so a fresh, resumed or cached run gives
equal results. Files of other tools that hold only ``name,lat,lon[,top_tiles]`` read too.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

from aeroloc.core.errors import AerolocError

# the status (after "not localized: ") of a query whose evidence points at two far-apart places
AMBIGUOUS = "two places match"
STAGES = ("descriptor", "search", "local_features", "rerank", "sweep", "align")
COLUMNS = [
    "name",
    "lat",
    "lon",
    "status",
    "confidence",
    "sigma_m",
    "inliers",
    "top_tiles",
    "retrieved_tiles",
    *(f"{s}_ms" for s in STAGES),
    "total_ms",
]


@dataclass
class Localization:
    """One query's answer. ``lat, lon`` NaN = not localized (``status`` says why); ``top_tiles`` re-ranked best
    first, ``retrieved`` in retrieval order; ``times_ms`` per stage (:data:`STAGES`)."""

    name: str
    lat: float = math.nan
    lon: float = math.nan
    status: str = ""
    inliers: int = 0
    top_tiles: list[str] = field(default_factory=list)
    retrieved: list[str] = field(default_factory=list)
    times_ms: dict = field(default_factory=dict)
    confidence: float | None = None  # probability that the fix lies within its stated radius (calibrated)
    sigma_m: float | None = None  # 1-sigma position uncertainty, metres (None: not localized)
    best = None  # cascade.Candidate, for visualisation (not part of the CSV)
    dense = None  # dense_stage.DenseResult, for visualisation (not part of the CSV)
    placement = None  # sweep.Hypothesis a sweep fix confirmed: its heading and scale (a flight's pose; not in the CSV)
    refined_m = None  # metres the structure refinement moved a local-feature fix (None: not refined; not in the CSV)

    @property
    def localized(self) -> bool:
        return math.isfinite(self.lat) and math.isfinite(self.lon)

    @property
    def total_ms(self) -> float:
        return sum(self.times_ms.get(s, 0.0) for s in STAGES)

    def row(self) -> dict[str, str]:
        """The results-CSV row, all strings (coordinates to 1e-8 degrees, times to 0.01 ms)."""
        loc = self.localized
        r = {
            "name": self.name,
            "lat": f"{self.lat:.8f}" if loc else "",
            "lon": f"{self.lon:.8f}" if loc else "",
            "status": self.status,
            "confidence": "" if self.confidence is None else f"{self.confidence:.3f}",
            "sigma_m": "" if self.sigma_m is None else f"{self.sigma_m:.2f}",
            "inliers": str(self.inliers),
            "top_tiles": ";".join(self.top_tiles),
            "retrieved_tiles": ";".join(self.retrieved),
        }
        for s in STAGES:
            r[f"{s}_ms"] = f"{self.times_ms.get(s, 0.0):.2f}"
        # the sum of the written stage times, so a row read back (from_row) writes the same row again
        r["total_ms"] = f"{sum(float(r[f'{s}_ms']) for s in STAGES):.2f}"
        return r

    @classmethod
    def from_row(cls, row: dict, where: str = "results") -> Localization:
        """The result a CSV row holds (``where`` names the file and line in errors); columns beyond
        ``name,lat,lon`` are optional."""
        lat, lon = _coordinate(row, "lat", where), _coordinate(row, "lon", where)
        try:
            inliers = int(row.get("inliers") or 0)
            times = {s: float(row[f"{s}_ms"]) for s in STAGES if row.get(f"{s}_ms")}
            confidence = float(row["confidence"]) if row.get("confidence") else None
            sigma = float(row["sigma_m"]) if row.get("sigma_m") else None
        except ValueError:
            raise AerolocError(f"{where}: inliers, confidence, sigma_m or *_ms columns are not numbers") from None
        return cls(
            row["name"],
            lat,
            lon,
            row.get("status") or "",
            inliers,
            _ids(row.get("top_tiles")),
            _ids(row.get("retrieved_tiles")),
            times,
            confidence,
            sigma,
        )


def _ids(cell: str | None) -> list[str]:
    return [t for t in (cell or "").split(";") if t]


def _coordinate(row: dict, col: str, where: str) -> float:
    v = (row.get(col) or "").strip()
    if v in ("", "nan"):
        return math.nan
    try:
        return float(v)
    except ValueError:
        raise AerolocError(f"{where}: lat/lon {row.get('lat')!r},{row.get('lon')!r} are not numbers") from None


def read_localizations(path) -> list[Localization]:
    """Every result of a results CSV (``aeroloc localize``'s, ``aeroloc retrieve``'s, or any with
    ``name,lat,lon[,top_tiles]``)."""
    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: results file not found")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = {"name", "lat", "lon"} - set(reader.fieldnames or [])
        if missing:
            raise AerolocError(f"{path}: missing columns {sorted(missing)} (need name,lat,lon[,top_tiles])")
        return [Localization.from_row(r, f"{path}:{i}") for i, r in enumerate(reader, start=2)]
