"""Query sets: images with (optional) ground truth and (optional) priors.

Accepted shapes:
- a CSV with ``name`` and, when the truth is known, ``lat,lon`` (+ optional ``heading_deg``, ``alt_m``,
  ``footprint_m`` …, and the prior columns of :mod:`aeroloc.core.priors`: ``gsd_m, gsd_tol, alt_agl_m, hfov_deg,
  focal_mm, sensor_w_mm, heading_deg, heading_tol_deg``); images are looked up beside it, in a sibling
  ``queries/`` or ``photos/`` folder;
- the seed's ``queries.txt``: header line, then ``filename lon lat`` (longitude first!);
- a folder of photos whose EXIF holds GPS (lat, lon, altitude).

Truth and priors are kept apart. ``lat, lon`` and the ``heading_deg`` / ``gsd_m`` columns as written are truth,
for scoring (``Query.lat``, ``Query.lon``, ``Query.truth_heading_deg``, ``Query.truth_gsd_m``); what the
pipeline may use is ``Query.priors``, chosen by ``load_queries(..., priors=...)``: ``"auto"`` by default (a
user's CSV and EXIF are priors, a generated set's truth is not), ``"csv"``, ``"none"``, ``"exact"``, ``"rough"``.
The module docstring of :mod:`aeroloc.core.priors` says why and what each does. EXIF gives focal lengths and
``GPSImgDirection``; its GPS altitude (``Query.alt_m``) is above sea level and never becomes a height above ground.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

from aeroloc.core.errors import AerolocError
from aeroloc.core.priors import (
    GENERATED_SET_COLUMN,
    MODES,
    PRIOR_COLUMNS,
    TOL_FIELDS,
    TRUTH_COLUMNS,
    Priors,
    build_priors,
    hfov_from_35mm,
    parse_value,
    truth_priors,
)

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp"}
IMAGE_DIRS = ("queries", "photos", "images", ".")


@dataclass
class Query:
    name: str
    path: Path
    lat: float = math.nan  # ground truth (NaN when unknown)
    lon: float = math.nan
    heading_deg: float | None = None  # TRUTH: the set's heading_deg column as written (scoring only; see priors)
    alt_m: float | None = None  # GPS altitude above sea level (EXIF, alt_m column): not a height above ground
    extra: dict = field(default_factory=dict)  # the other columns, as text
    truth_gsd_m: float | None = None  # TRUTH: gsd_m column, or footprint_m / width of a square generated query
    priors: Priors = field(default_factory=Priors)  # what the pipeline may use (load_queries(priors=...))
    origin: str = ""  # where the query was read ("file:line", the photo), for messages

    @property
    def has_truth(self) -> bool:
        return math.isfinite(self.lat) and math.isfinite(self.lon)

    @property
    def truth_heading_deg(self) -> float | None:
        """The set's heading, for scoring (the same as ``heading_deg``, named for what it is)."""
        return self.heading_deg


def load_queries(path, require_images: bool = True, *, priors: str = "auto", seed: int = 0) -> list[Query]:
    """The queries of ``path`` (a CSV, a queries.txt, a folder holding one, or a folder of photos).

    ``priors`` (:data:`aeroloc.core.priors.MODES`) decides what becomes ``Query.priors``; truth is kept either
    way. ``seed`` is the noise seed of ``"rough"``. Images are only needed when ``require_images``; where they
    exist their width and EXIF are read (header only) for the priors."""
    if priors not in MODES:
        raise AerolocError(f"priors mode {priors!r} unknown (one of {', '.join(MODES)})")
    path = Path(path)
    if not path.exists():
        raise AerolocError(f"{path}: query set not found")
    if path.is_dir():
        if (path / "queries.csv").is_file():
            return load_queries(path / "queries.csv", require_images, priors=priors, seed=seed)
        if (path / "queries.txt").is_file():
            return load_queries(path / "queries.txt", require_images, priors=priors, seed=seed)
        return _from_exif_folder(path, priors, seed)
    if path.suffix.lower() == ".txt":
        queries = _from_seed_txt(path, priors)
    else:
        queries = _from_csv(path, priors, seed)
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


def _from_csv(path: Path, mode: str = "auto", seed: int = 0) -> list[Query]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        cols = set(reader.fieldnames or [])
        # truth is optional (photos to localize have none: name and prior columns only), but whole
        missing = ({"name"} | ({"lat", "lon"} if cols & {"lat", "lon"} else set())) - cols
        if missing:
            raise AerolocError(
                f"{path}: missing columns {sorted(missing)} (need name; lat,lon together when the truth is known)"
            )
        rows = list(reader)
    if not rows:
        raise AerolocError(f"{path}: no queries")
    folder = _image_dir(path, rows[0]["name"])
    generated = GENERATED_SET_COLUMN in cols  # its heading_deg / gsd_m are the generator's truth
    known = {"name", "lat", "lon", "heading_deg", "alt_m", *PRIOR_COLUMNS}
    out = []
    for i, r in enumerate(rows, start=2):
        where = f"{path}:{i}"
        if None in r or None in r.values():  # csv.DictReader's marks for too many / too few fields
            raise AerolocError(f"{where}: the row does not have the header's {len(cols)} columns")
        lat, lon = _float(r.get("lat"), "lat", where), _float(r.get("lon"), "lon", where)
        _check_latlon(lat, lon, where)
        values = {c: parse_value(c, r[c], where) for c in PRIOR_COLUMNS if c in cols}
        image = folder / r["name"]
        width, height, cam, cam_src = exif_camera(image)
        truth_gsd = values.get("gsd_m")
        if truth_gsd is None and generated and "gsd_m" not in cols and width and width == height:
            truth_gsd = _footprint_gsd(r[GENERATED_SET_COLUMN], width)
        q = Query(
            r["name"],
            image,
            math.nan if lat is None else lat,
            math.nan if lon is None else lon,
            values.get("heading_deg"),
            _float(r.get("alt_m"), "alt_m", where),
            {k: v for k, v in r.items() if k not in known},
            truth_gsd,
            origin=where,
        )
        if mode in ("auto", "csv"):
            given = {k: v for k, v in values.items() if v is not None}
            if mode == "auto" and generated:
                for k in TRUTH_COLUMNS:
                    given.pop(k, None)
            sources = dict.fromkeys(given, "csv")
            for k, v in cam.items():  # EXIF fills what the CSV leaves blank
                if k not in given:
                    given[k], sources[k] = v, cam_src[k]
            q.priors = build_priors(given, sources, width_px=width, where=where)
        elif mode in ("exact", "rough"):
            tol = {k: values.get(k) for k in TOL_FIELDS}
            q.priors = truth_priors(truth_gsd, q.truth_heading_deg, width_px=width, tolerances=tol)
            if mode == "rough":
                q.priors = q.priors.perturbed(seed, q.name)
        else:  # "none": nothing known, but the width stays for flags that derive a ground resolution
            q.priors = Priors(width_px=width)
        out.append(q)
    return out


def _footprint_gsd(raw, width: int) -> float | None:
    """The truth ground resolution of a square generated query: its ground side over its width (the column is
    only ever text in ``extra``, so a blank or odd cell is no truth rather than an error)."""
    try:
        side = float(raw)
    except ValueError:
        return None
    return side / width if math.isfinite(side) and side > 0 else None


def _check_latlon(lat, lon, where):
    if lat is not None and not -90 <= lat <= 90:
        raise AerolocError(f"{where}: latitude {lat} out of range (is the file lon-first?)")
    if lon is not None and not -180 <= lon <= 180:
        raise AerolocError(f"{where}: longitude {lon} out of range")


def _from_seed_txt(path: Path, mode: str = "auto") -> list[Query]:
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
        q = Query(parts[0], folder / parts[0], lat, lon, origin=f"{path}:{i}")
        q.priors = _photo_priors(q.path, mode, q.origin)
        out.append(q)
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


def exif_camera(path: Path) -> tuple[int | None, int | None, dict[str, float], dict[str, str]]:
    """(width, height) in pixels as shown (EXIF orientation applied) and the priors a photo's EXIF carries:
    ``focal_mm`` (FocalLength), ``hfov_deg`` (from FocalLengthIn35mmFilm), ``heading_deg`` (GPSImgDirection),
    with their sources. Nothing for a missing or unreadable file; EXIF's 0 ("unknown") and broken values are
    left out. GPS altitude is not used: it is above sea level, not above ground."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            exif = im.getexif()
            sub = exif.get_ifd(0x8769)
            gps = exif.get_ifd(0x8825)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError):
        return None, None, {}, {}
    if exif.get(0x0112) in (5, 6, 7, 8):  # turned a quarter: shown width is the stored height
        w, h = h, w

    def num(v):
        try:
            v = float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
        return v if math.isfinite(v) else None

    values, sources = {}, {}
    focal = num(sub.get(0x920A, exif.get(0x920A)))  # the Exif sub-IFD (some writers put it in IFD0)
    if focal is not None and focal > 0:
        values["focal_mm"], sources["focal_mm"] = focal, "exif FocalLength"
    f35 = num(sub.get(0xA405, exif.get(0xA405)))
    if f35 is not None and f35 > 0:
        values["hfov_deg"], sources["hfov_deg"] = hfov_from_35mm(f35), "exif FocalLengthIn35mmFilm"
    direction = num(gps.get(17))
    if direction is not None and 0 <= direction <= 360:
        ref = gps.get(16)
        magnetic = ref in ("M", b"M")
        values["heading_deg"] = direction % 360.0
        sources["heading_deg"] = "exif GPSImgDirection" + (" (magnetic north)" if magnetic else "")
    return w, h, values, sources


def image_files(folder: Path, instead: str) -> list[Path]:
    """The images of ``folder`` in name order; a one-line error naming what else was looked for when none."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise AerolocError(f"{folder}: no images (and no {instead})")
    return files


def _from_exif_folder(folder: Path, mode: str = "auto", seed: int = 0) -> list[Query]:
    files = image_files(folder, "queries.csv / queries.txt")
    out = []
    for p in files:
        g = exif_gps(p)
        lat, lon, alt = g if g else (math.nan, math.nan, None)
        q = Query(p.name, p, lat, lon, None, alt, origin=str(p))
        q.priors = _photo_priors(p, mode, str(p))
        out.append(q)
    return out


def _photo_priors(image: Path, mode: str, where: str) -> Priors:
    """A query without prior columns or truth heading/resolution: its EXIF's priors ("auto", "csv"), else none
    ("exact" and "rough" have no truth to start from)."""
    width, _, cam, cam_src = exif_camera(image)
    if mode in ("auto", "csv"):
        return build_priors(cam, cam_src, width_px=width, where=where)
    return Priors(width_px=width)
