"""Query sets: images with (optional) ground-truth positions.

Accepted shapes:
- a CSV with ``name,lat,lon`` (+ optional ``heading_deg``, ``alt_m``, ``footprint_m`` …); images are looked up
  beside it, in a sibling ``queries/`` or ``photos/`` folder;
- the seed's ``queries.txt``: header line, then ``filename lon lat`` (longitude first!);
- a folder of photos whose EXIF holds GPS (lat, lon, altitude).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

from aeroloc.core.errors import AerolocError

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp"}
IMAGE_DIRS = ("queries", "photos", "images", ".")


@dataclass
class Query:
    name: str
    path: Path
    lat: float = math.nan  # ground truth (NaN when unknown)
    lon: float = math.nan
    heading_deg: float | None = None
    alt_m: float | None = None
    extra: dict = field(default_factory=dict)

    @property
    def has_truth(self) -> bool:
        return math.isfinite(self.lat) and math.isfinite(self.lon)


def load_queries(path, require_images: bool = True) -> list[Query]:
    path = Path(path)
    if not path.exists():
        raise AerolocError(f"{path}: query set not found")
    if path.is_dir():
        if (path / "queries.csv").is_file():
            return load_queries(path / "queries.csv", require_images)
        if (path / "queries.txt").is_file():
            return load_queries(path / "queries.txt", require_images)
        return _from_exif_folder(path)
    if path.suffix.lower() == ".txt":
        queries = _from_seed_txt(path)
    else:
        queries = _from_csv(path)
    if require_images:
        for q in queries:
            if not q.path.is_file():
                raise AerolocError(
                    f"{path}: image for query '{q.name}' not found (looked beside it and in "
                    f"{', '.join(d for d in IMAGE_DIRS if d != '.')}/)"
                )
    return queries


def _image_dir(listing: Path, first_name: str) -> Path:
    for d in IMAGE_DIRS:
        if (listing.parent / d / first_name).is_file():
            return listing.parent / d
    return listing.parent


def _float(v, what, where):
    if v is None or str(v).strip() == "":
        return None
    try:
        return float(v)
    except ValueError:
        raise AerolocError(f"{where}: {what} {v!r} is not a number") from None


def _from_csv(path: Path) -> list[Query]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        cols = set(reader.fieldnames or [])
        missing = {"name", "lat", "lon"} - cols
        if missing:
            raise AerolocError(f"{path}: missing columns {sorted(missing)} (need name,lat,lon)")
        rows = list(reader)
    if not rows:
        raise AerolocError(f"{path}: no queries")
    folder = _image_dir(path, rows[0]["name"])
    out = []
    for i, r in enumerate(rows, start=2):
        where = f"{path}:{i}"
        if None in r or None in r.values():  # csv.DictReader's marks for too many / too few fields
            raise AerolocError(f"{where}: the row does not have the header's {len(cols)} columns")
        lat, lon = _float(r["lat"], "lat", where), _float(r["lon"], "lon", where)
        _check_latlon(lat, lon, where)
        extra = {k: v for k, v in r.items() if k not in {"name", "lat", "lon", "heading_deg", "alt_m"}}
        out.append(
            Query(
                r["name"],
                folder / r["name"],
                math.nan if lat is None else lat,
                math.nan if lon is None else lon,
                _float(r.get("heading_deg"), "heading_deg", where),
                _float(r.get("alt_m"), "alt_m", where),
                extra,
            )
        )
    return out


def _check_latlon(lat, lon, where):
    if lat is not None and not -90 <= lat <= 90:
        raise AerolocError(f"{where}: latitude {lat} out of range (is the file lon-first?)")
    if lon is not None and not -180 <= lon <= 180:
        raise AerolocError(f"{where}: longitude {lon} out of range")


def _from_seed_txt(path: Path) -> list[Query]:
    lines = [ln for ln in path.read_text().splitlines()[1:] if ln.strip()]
    if not lines:
        raise AerolocError(f"{path}: no queries")
    folder = _image_dir(path, lines[0].split()[0])
    out = []
    for i, ln in enumerate(lines, start=2):
        parts = ln.split()
        if len(parts) < 3:
            raise AerolocError(f"{path}:{i}: expected 'filename lon lat', got {ln!r}")
        lon, lat = _float(parts[1], "lon", f"{path}:{i}"), _float(parts[2], "lat", f"{path}:{i}")
        _check_latlon(lat, lon, f"{path}:{i}")
        out.append(Query(parts[0], folder / parts[0], lat, lon))
    return out


def exif_gps(path: Path) -> tuple[float, float, float | None] | None:
    """(lat, lon, altitude) from a photo's EXIF GPS block, or None."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            gps = im.getexif().get_ifd(0x8825)
    except (UnidentifiedImageError, OSError):
        return None
    if not gps or 2 not in gps or 4 not in gps:
        return None

    def deg(v):
        d, m, s = (float(x) for x in v)
        return d + m / 60 + s / 3600

    lat = deg(gps[2]) * (-1 if gps.get(1, "N") in ("S", b"S") else 1)
    lon = deg(gps[4]) * (-1 if gps.get(3, "E") in ("W", b"W") else 1)
    alt = float(gps[6]) * (-1 if gps.get(5) in (1, b"\x01") else 1) if 6 in gps else None
    return lat, lon, alt


def _from_exif_folder(folder: Path) -> list[Query]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise AerolocError(f"{folder}: no images (and no queries.csv / queries.txt)")
    out = []
    for p in files:
        g = exif_gps(p)
        lat, lon, alt = g if g else (math.nan, math.nan, None)
        out.append(Query(p.name, p, lat, lon, None, alt))
    return out
