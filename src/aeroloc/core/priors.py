"""Per-query priors: what the aircraft knows about its ground resolution and heading, each optional.

"Anywhere, any heading, any scale": a drone knows its heading to about ±15° and its ground resolution to about
±25 %, or not at all. A :class:`Priors` holds what is known for one query; anything unknown is ``None`` and the
pipeline searches it (every heading, every scale).

Columns of a query CSV (all optional, blank = unknown) and the matching ``aeroloc`` flags
(:mod:`aeroloc.commands.priors_args`):

================  ================  ======================================================================
column            flag              meaning (unit, valid range)
================  ================  ======================================================================
``gsd_m``         ``--gsd``         ground size of one query pixel, metres (> 0)
``gsd_tol``       ``--gsd-tol``     relative tolerance of the ground resolution, in (0, 1); default 0.25:
                                    the truth lies in ``gsd_m · [1 - tol, 1 + tol]``
``alt_agl_m``     ``--alt-agl``     height above GROUND, metres (> 0); not the GPS altitude above sea level
``hfov_deg``      ``--hfov``        horizontal field of view of the camera, degrees, in (0, 180)
``focal_mm``      ``--focal-mm``    focal length, mm (> 0)
``sensor_w_mm``   ``--sensor-w-mm`` sensor width, mm (> 0)
``heading_deg``   ``--heading``     where the top of the image points, degrees clockwise from north (any
                                    number, kept modulo 360 in [0, 360))
``heading_tol_deg`` ``--heading-tol`` heading tolerance, degrees, in [0, 180]; default 15 (180 = unknown)
================  ================  ======================================================================

Ground resolution, in metres per pixel of the image as stored (``width_px`` pixels wide, EXIF orientation applied):

- given: ``gsd_m``;
- from height above ground and field of view: ``gsd = 2 · alt_agl_m · tan(hfov_deg / 2) / width_px``;
- from height above ground, focal length and sensor width: ``gsd = alt_agl_m · sensor_w_mm / (focal_mm · width_px)``.

When several are given they must agree: each derived value must lie within ``gsd_tol`` of the first (given >
field of view > focal length; a camera value read from EXIF yields to one the user wrote); otherwise loading fails
naming both. From EXIF (:mod:`aeroloc.core.queries`) come ``FocalLength`` (``focal_mm``),
``FocalLengthIn35mmFilm`` (``hfov_deg = 2 · atan(36 / (2 · f35))``, the 36 mm width of a full frame; on a 4:3
sensor this is about 3 % wider than the diagonal-based equivalent, far inside the tolerance) and
``GPSImgDirection`` (``heading_deg``). EXIF's ``GPSAltitude`` is above sea level and never taken as a height
above ground: without ``alt_agl_m`` (or ``--alt-agl``) a photo has no ground-resolution prior.

Where a prior came from is kept (``gsd_source``, ``heading_source``): ``csv``, ``exif <Tag>``, a flag
(``--gsd``), ``truth``, and ``+ noise (seed N)`` when perturbed.

Truth is not a prior. The generated query sets of ``../shared/data`` (naip-nd, multi-region) write the EXACT
heading and ground resolution of every query into ``heading_deg`` / ``gsd_m`` (they also have a ``footprint_m``
column, the ground side of the query, which only a generator knows). Reading those as priors would let the
truth leak into the estimate. :func:`aeroloc.core.queries.load_queries` therefore keeps the columns as truth
(``Query.truth_heading_deg``, ``Query.truth_gsd_m``, for scoring) and decides separately what becomes a prior,
by ``priors=`` (:data:`MODES`):

- ``"auto"`` (default): a user's CSV means what it says, its prior columns (and the photos' EXIF) are priors;
  but in a generated set (a ``footprint_m`` column) ``heading_deg`` and ``gsd_m`` are truth only. So
  ``aeroloc localize`` on a user's flight log uses its compass, and on a benchmark set never sees the answer.
- ``"csv"``: every prior column is a prior, generated set or not (you vouch for the file).
- ``"none"``: no priors at all; the pipeline searches every heading and scale.
- ``"exact"``: the truth as the prior (tolerances from ``gsd_tol`` / ``heading_tol_deg`` or the defaults): the
  best case for a benchmark.
- ``"rough"``: the truth with real-sensor-like noise, deterministic per query name and ``seed``: ground resolution
  times a factor uniform in [0.8, 1.25], heading shifted uniformly within ±15°. The default tolerances still
  contain the truth (1/1.25 = 0.8 ≥ 1 - 0.25; 15° ≤ 15°).

Benchmarks pass ``"none"``, ``"rough"`` or ``"exact"`` explicitly; ``"rough"`` equals ``"exact"`` followed by
:func:`apply_overrides` with ``perturb_seed``.

Command-line overrides (:class:`PriorOverrides`, applied by :func:`apply_overrides`): ``no_priors`` drops every
prior of the file; ``from_truth`` uses the set's truth instead (benchmarks); each value flag replaces its field
for every query. A ground-resolution flag restates the ground resolution: ``--gsd`` replaces all of the file's
ground-resolution fields (``gsd_m``, ``alt_agl_m``, camera), ``--alt-agl`` / ``--hfov`` / ``--focal-mm`` /
``--sensor-w-mm`` replace the file's ``gsd_m`` and their own field, the rest of the camera still coming from the
file or EXIF. ``perturb_seed`` then adds the noise of ``"rough"`` to whatever priors result.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Protocol, TypeVar

from aeroloc.core.errors import AerolocError

DEFAULT_GSD_TOL = 0.25
DEFAULT_HEADING_TOL_DEG = 15.0
ROUGH_GSD_FACTOR = (0.8, 1.25)  # "rough" / perturb: ground resolution times a factor uniform in this range
ROUGH_HEADING_DEG = 15.0  # "rough" / perturb: heading shifted uniformly within ± this
FULL_FRAME_WIDTH_MM = 36.0  # the width a 35 mm-equivalent focal length refers to
MODES = ("auto", "csv", "none", "exact", "rough")
GENERATED_SET_COLUMN = "footprint_m"  # a CSV with this column is a generated set: heading_deg, gsd_m are truth

GSD_FIELDS = ("gsd_m", "alt_agl_m", "hfov_deg", "focal_mm", "sensor_w_mm")
CAMERA_FIELDS = ("alt_agl_m", "hfov_deg", "focal_mm", "sensor_w_mm")
TOL_FIELDS = ("gsd_tol", "heading_tol_deg")
PRIOR_COLUMNS = (
    "gsd_m",
    "gsd_tol",
    "alt_agl_m",
    "hfov_deg",
    "focal_mm",
    "sensor_w_mm",
    "heading_deg",
    "heading_tol_deg",
)
TRUTH_COLUMNS = ("heading_deg", "gsd_m")  # written by the generated sets as exact truth

# column -> (valid?, what a valid value is)
_RULES = {
    "gsd_m": (lambda v: v > 0, "must be > 0 (metres of ground per query pixel)"),
    "gsd_tol": (lambda v: 0 < v < 1, "must be between 0 and 1, exclusive (relative: 0.25 = ±25 %)"),
    "alt_agl_m": (lambda v: v > 0, "must be > 0 (height above ground in metres, not altitude above sea level)"),
    "hfov_deg": (lambda v: 0 < v < 180, "must be between 0 and 180 degrees, exclusive (horizontal field of view)"),
    "focal_mm": (lambda v: v > 0, "must be > 0 (focal length in mm)"),
    "sensor_w_mm": (lambda v: v > 0, "must be > 0 (sensor width in mm)"),
    "heading_deg": (lambda v: True, ""),
    "heading_tol_deg": (lambda v: 0 <= v <= 180, "must be between 0 and 180 degrees"),
}


def parse_value(name: str, raw, where: str, label: str | None = None) -> float | None:
    """``raw`` (a CSV cell, flag text or number) as a valid value of prior ``name``, None when blank.

    Failures are one-line :class:`AerolocError`s ``"{where}: {label} {raw!r} ..."`` (``label`` defaults to
    the column name; the CLI passes its flag)."""
    label = label or name
    if raw is None or (isinstance(raw, str) and raw.strip() == ""):
        return None
    try:
        v = float(raw)
    except (TypeError, ValueError):
        raise AerolocError(f"{where}: {label} {raw!r} is not a number") from None
    if not math.isfinite(v):
        raise AerolocError(f"{where}: {label} {raw!r} is not a finite number")
    ok, rule = _RULES[name]
    if not ok(v):
        raise AerolocError(f"{where}: {label} {v:g} {rule}")
    return v


def gsd_from_hfov(alt_agl_m: float, hfov_deg: float, width_px: int) -> float:
    """Metres per pixel of a nadir image ``width_px`` wide, from height above ground and horizontal field of view."""
    return 2.0 * alt_agl_m * math.tan(math.radians(hfov_deg) / 2.0) / width_px


def gsd_from_focal(alt_agl_m: float, focal_mm: float, sensor_w_mm: float, width_px: int) -> float:
    """Metres per pixel of a nadir image ``width_px`` wide, from height above ground, focal length, sensor width."""
    return alt_agl_m * sensor_w_mm / (focal_mm * width_px)


def hfov_from_35mm(focal_35mm: float) -> float:
    """Horizontal field of view (degrees) of a 35 mm-equivalent focal length: ``2 · atan(36 / (2 · f35))``."""
    return math.degrees(2.0 * math.atan(FULL_FRAME_WIDTH_MM / (2.0 * focal_35mm)))


def perturbation(seed: int, key: str) -> tuple[float, float]:
    """(ground-resolution factor in [0.8, 1.25], heading shift in [-15°, 15°]) for query ``key`` under ``seed``.

    A hash of both, so the same query gets the same noise whatever the order or subset of the set, on any
    machine; both are drawn for every query, so one prior's noise does not depend on whether the other exists."""
    d = hashlib.sha256(f"aeroloc-priors\0{int(seed)}\0{key}".encode()).digest()
    u1 = int.from_bytes(d[:8], "big") / 2.0**64
    u2 = int.from_bytes(d[8:16], "big") / 2.0**64
    lo, hi = ROUGH_GSD_FACTOR
    return lo + (hi - lo) * u1, ROUGH_HEADING_DEG * (2.0 * u2 - 1.0)


def _named(name: str, source: str) -> str:
    """How a value is named in a message: its flag, or its column and where it came from."""
    return source if source.startswith("--") else f"{name} ({source})"


def _rank(source: str) -> int:
    return 1 if source.startswith("exif") else 0  # camera facts the user wrote beat EXIF's


@dataclass(frozen=True)
class Priors:
    """What is known about one query; ``None`` = unknown (the pipeline searches it). See the module docstring."""

    gsd_m: float | None = None  # metres per pixel of the image ``width_px`` wide (given or derived)
    gsd_tol: float = DEFAULT_GSD_TOL  # relative, in (0, 1)
    heading_deg: float | None = None  # clockwise from north, [0, 360)
    heading_tol_deg: float = DEFAULT_HEADING_TOL_DEG  # degrees, [0, 180]
    alt_agl_m: float | None = None  # the inputs the ground resolution can be derived from
    hfov_deg: float | None = None
    focal_mm: float | None = None
    sensor_w_mm: float | None = None
    width_px: int | None = None  # width of the image gsd_m refers to (None: the image file, not yet read)
    gsd_source: str | None = None  # e.g. "gsd_m (csv)", "--alt-agl + hfov_deg (exif FocalLengthIn35mmFilm)"
    heading_source: str | None = None
    # how gsd_m was had: "gsd_m" (given) or the derivation, "alt_agl_m+hfov_deg" / "alt_agl_m+focal_mm+sensor_w_mm"
    gsd_from: str | None = None
    sources: tuple[tuple[str, str], ...] = field(default=(), repr=False)  # (field, source) of every given input

    @property
    def known(self) -> bool:
        """Anything known at all."""
        return self.gsd_m is not None or self.heading_deg is not None

    def source(self, name: str) -> str | None:
        """Where input ``name`` (a column of :data:`PRIOR_COLUMNS`) came from, None if not given."""
        return dict(self.sources).get(name)

    def gsd_range(self) -> tuple[float, float] | None:
        """(lo, hi) metres per pixel the truth lies in, ``gsd_m · (1 ∓ gsd_tol)``; None when unknown."""
        if self.gsd_m is None:
            return None
        return self.gsd_m * (1.0 - self.gsd_tol), self.gsd_m * (1.0 + self.gsd_tol)

    def heading_range(self) -> tuple[float, float] | None:
        """(lo, hi) degrees clockwise from north, ``heading_deg ∓ heading_tol_deg``, NOT wrapped (lo may be < 0,
        hi ≥ 360: the headings ``a`` with ``lo <= a <= hi`` modulo 360); None when unknown."""
        if self.heading_deg is None:
            return None
        return self.heading_deg - self.heading_tol_deg, self.heading_deg + self.heading_tol_deg

    @property
    def heading(self) -> tuple[float, float] | None:
        """(heading, tolerance) degrees when the heading says something (known, tolerance under 180°), else None."""
        if self.heading_deg is None or self.heading_tol_deg >= 180.0:
            return None
        return float(self.heading_deg), float(self.heading_tol_deg)

    def heading_contains(self, angle_deg: float) -> bool:
        """``angle_deg`` (any turn) is within the tolerance of the heading; True when the heading is unknown."""
        if self.heading_deg is None:
            return True
        gap = abs((angle_deg - self.heading_deg + 180.0) % 360.0 - 180.0)
        return gap <= self.heading_tol_deg + 1e-9

    def heading_search(self, step_deg: float = 7.5) -> tuple[float, ...] | None:
        """Headings to try, degrees in (-180, 180] (signed, as the dense stage's turns): the tolerance range
        from end to end at most ``step_deg`` apart; None when unknown (search the full circle)."""
        if self.heading_deg is None:
            return None
        if step_deg <= 0:
            raise ValueError(f"step_deg must be > 0, got {step_deg}")
        tol = self.heading_tol_deg
        if tol >= 180.0:
            n = math.ceil(360.0 / step_deg)
            angles = [self.heading_deg + 360.0 * k / n for k in range(n)]
        elif tol == 0:
            angles = [self.heading_deg]
        else:
            n = math.ceil(2.0 * tol / step_deg)
            angles = [self.heading_deg - tol + 2.0 * tol * k / n for k in range(n + 1)]
        return tuple(_signed(a) for a in angles)

    def with_image_width(self, width_px: int, where: str = "") -> Priors:
        """These priors for the query image ``width_px`` pixels wide: the ground resolution derived from the
        camera if it was waiting for the width, or rescaled if it was known for another width (a resized query).
        ``where`` prefixes the error if the camera's two derivations disagree."""
        width_px = int(width_px)
        if width_px <= 0:
            raise ValueError(f"image width must be > 0 px, got {width_px}")
        if self.width_px == width_px:
            return self
        if self.gsd_m is not None:
            k = 1.0 if self.width_px is None else self.width_px / width_px
            return replace(self, gsd_m=self.gsd_m * k, width_px=width_px)
        return build_priors(self.inputs(), dict(self.sources), width_px=width_px, where=where)

    def for_view(self, width_px: int, turn_deg: float = 0.0) -> Priors:
        """These priors for a view of the same pixels: a window ``width_px`` wide cut from the image (its ground
        resolution unchanged, where :meth:`with_image_width` would rescale it for a resized image), turned
        ``turn_deg`` (OpenCV, counter-clockwise) first, which takes that much from the heading."""
        out = replace(self, width_px=int(width_px))
        if self.heading_deg is not None and turn_deg:
            out = replace(out, heading_deg=_wrap360(self.heading_deg - turn_deg))
        return out

    def perturbed(self, seed: int, key: str) -> Priors:
        """The known values with the noise of :func:`perturbation` (``key``: the query name). The result's ground
        resolution is a given value (the camera inputs it came from are dropped: they would contradict it)."""
        factor, shift = perturbation(seed, key)
        noise = f" + noise (seed {int(seed)})"
        out = self
        if self.gsd_m is not None:
            src = (self.gsd_source or "gsd_m") + noise
            keep = tuple((k, s) for k, s in self.sources if k not in GSD_FIELDS) + (("gsd_m", src),)
            out = replace(
                out,
                **dict.fromkeys(CAMERA_FIELDS),
                gsd_m=self.gsd_m * factor,
                gsd_source=src,
                gsd_from="gsd_m",
                sources=keep,
            )
        if self.heading_deg is not None:
            src = (self.heading_source or "heading_deg") + noise
            keep = tuple((k, s) for k, s in out.sources if k != "heading_deg") + (("heading_deg", src),)
            out = replace(out, heading_deg=_wrap360(self.heading_deg + shift), heading_source=src, sources=keep)
        return out

    def inputs(self) -> dict[str, float]:
        """The given values (not the derived ground resolution), as :func:`build_priors` takes them."""
        given = dict(self.sources)
        out = {k: getattr(self, k) for k in CAMERA_FIELDS if getattr(self, k) is not None}
        if self.gsd_m is not None and self.gsd_from == "gsd_m":
            out["gsd_m"] = self.gsd_m  # at width_px, which goes back to build_priors with it
        if self.heading_deg is not None:
            out["heading_deg"] = self.heading_deg
        out.update({k: getattr(self, k) for k in TOL_FIELDS if k in given})
        return out

    def describe(self) -> str:
        """One line: what is known and from where."""
        parts = []
        if self.gsd_m is not None:
            parts.append(f"gsd {self.gsd_m:.4g} m/px ±{self.gsd_tol * 100:g} % from {self.gsd_source}")
        if self.heading_deg is not None:
            parts.append(f"heading {self.heading_deg:.1f}° ±{self.heading_tol_deg:g}° from {self.heading_source}")
        cam = [f"{k} {getattr(self, k):.4g}" for k in CAMERA_FIELDS if getattr(self, k) is not None]
        if self.gsd_m is None and cam:
            parts.append(f"camera {', '.join(cam)} but ground resolution unknown")
        return "; ".join(parts) if self.known else "; ".join(["no priors", *parts])


def _wrap360(a: float) -> float:
    """Degrees in [0, 360) (``-1e-20 % 360`` is 360.0 in floating point)."""
    a = a % 360.0
    return 0.0 if a >= 360.0 else a


def _signed(a: float) -> float:
    """Degrees in (-180, 180]."""
    a = a % 360.0
    return a - 360.0 if a > 180.0 else a


def build_priors(
    values: Mapping[str, float | None],
    sources: Mapping[str, str],
    *,
    width_px: int | None = None,
    where: str = "",
) -> Priors:
    """Priors from given ``values`` (columns of :data:`PRIOR_COLUMNS`, already parsed by :func:`parse_value`;
    None = not given) and where each came from (``sources``: ``"csv"``, ``"exif <Tag>"``, a flag ...).

    Resolves the ground resolution (given, or derived when the image width is known) and fails with a one-line
    :class:`AerolocError` ``"{where}: ..."`` naming both values when two of its sources disagree by more than
    ``gsd_tol``."""
    vals = {k: float(v) for k, v in values.items() if v is not None}
    srcs = {k: sources.get(k, "csv") for k in vals}
    gsd_tol = vals.get("gsd_tol", DEFAULT_GSD_TOL)
    heading_tol = vals.get("heading_tol_deg", DEFAULT_HEADING_TOL_DEG)
    prefix = f"{where}: " if where else ""

    gsd, gsd_from, gsd_source = _resolve_gsd(_gsd_ways(vals, srcs, width_px), gsd_tol, prefix, srcs)

    heading = vals.get("heading_deg")
    return Priors(
        gsd_m=gsd,
        gsd_tol=gsd_tol,
        heading_deg=None if heading is None else _wrap360(heading),
        heading_tol_deg=heading_tol,
        alt_agl_m=vals.get("alt_agl_m"),
        hfov_deg=vals.get("hfov_deg"),
        focal_mm=vals.get("focal_mm"),
        sensor_w_mm=vals.get("sensor_w_mm"),
        width_px=int(width_px) if width_px else None,
        gsd_source=gsd_source,
        heading_source=None if heading is None else _named("heading_deg", srcs["heading_deg"]),
        gsd_from=gsd_from,
        sources=tuple((k, srcs[k]) for k in PRIOR_COLUMNS if k in srcs),
    )


def _gsd_ways(vals: dict, srcs: dict, width_px: int | None) -> list[tuple]:
    """Every way the ground resolution can be had, best first (the given value, then derivations, the user's
    before EXIF's): (rank, order, gsd, how, description)."""
    ways = []
    if "gsd_m" in vals:
        g = vals["gsd_m"]
        ways.append((-1, 0, g, "gsd_m", f"{_named('gsd_m', srcs['gsd_m'])} = {g:g} m/px"))
    alt = vals.get("alt_agl_m")
    if alt is not None and width_px:
        a_name = f"{_named('alt_agl_m', srcs['alt_agl_m'])} = {alt:g} m"
        if "hfov_deg" in vals:
            g = gsd_from_hfov(alt, vals["hfov_deg"], width_px)
            r = max(_rank(srcs["alt_agl_m"]), _rank(srcs["hfov_deg"]))
            desc = f"{a_name} with {_named('hfov_deg', srcs['hfov_deg'])} = {vals['hfov_deg']:g}°"
            ways.append((r, 1, g, "alt_agl_m+hfov_deg", f"{desc} (giving {g:.4g} m/px at {width_px} px wide)"))
        if "focal_mm" in vals and "sensor_w_mm" in vals:
            g = gsd_from_focal(alt, vals["focal_mm"], vals["sensor_w_mm"], width_px)
            r = max(_rank(srcs[k]) for k in ("alt_agl_m", "focal_mm", "sensor_w_mm"))
            desc = (
                f"{a_name} with {_named('focal_mm', srcs['focal_mm'])} = {vals['focal_mm']:g} mm and "
                f"{_named('sensor_w_mm', srcs['sensor_w_mm'])} = {vals['sensor_w_mm']:g} mm"
            )
            how = "alt_agl_m+focal_mm+sensor_w_mm"
            ways.append((r, 2, g, how, f"{desc} (giving {g:.4g} m/px at {width_px} px wide)"))
    ways.sort(key=lambda w: (w[0], w[1]))
    return ways


def _resolve_gsd(ways: list[tuple], gsd_tol: float, prefix: str, srcs: dict):
    """(gsd, how, source) from the best way; every other way must agree within ``gsd_tol``."""
    if not ways:
        return None, None, None
    _, _, gsd, gsd_from, first = ways[0]
    lo, hi = gsd * (1.0 - gsd_tol), gsd * (1.0 + gsd_tol)
    for _, _, g, _, other in ways[1:]:
        if not lo * (1 - 1e-9) <= g <= hi * (1 + 1e-9):
            raise AerolocError(
                f"{prefix}{first} contradicts {other}: more than gsd_tol {gsd_tol:g} (±{gsd_tol * 100:g} %) apart"
            )
    return gsd, gsd_from, " + ".join(_named(k, srcs[k]) for k in gsd_from.split("+"))


def truth_priors(
    truth_gsd_m: float | None,
    truth_heading_deg: float | None,
    *,
    width_px: int | None = None,
    tolerances: Mapping[str, float | None] | None = None,
) -> Priors:
    """The truth as priors (``"exact"``), with the given tolerances (``gsd_tol``, ``heading_tol_deg``) or the
    defaults."""
    tol = {k: v for k, v in (tolerances or {}).items() if k in TOL_FIELDS and v is not None}
    values = {"gsd_m": truth_gsd_m, "heading_deg": truth_heading_deg, **tol}
    sources = {"gsd_m": "truth", "heading_deg": "truth", **dict.fromkeys(tol, "csv")}
    return build_priors(values, sources, width_px=width_px)


# ---------------------------------------------------------------------------------------------------- overrides

_FLAGS = {  # field -> its command-line flag
    "gsd_m": "--gsd",
    "gsd_tol": "--gsd-tol",
    "alt_agl_m": "--alt-agl",
    "hfov_deg": "--hfov",
    "focal_mm": "--focal-mm",
    "sensor_w_mm": "--sensor-w-mm",
    "heading_deg": "--heading",
    "heading_tol_deg": "--heading-tol",
}


@dataclass(frozen=True)
class PriorOverrides:
    """What the command line says about every query's priors (:func:`apply_overrides`); None/False = keep the
    file's. Values (numbers, or the flags' text) are parsed and checked like the CSV's, the message naming the
    flag; ``perturb_seed`` is an integer."""

    gsd_m: float | None = None
    gsd_tol: float | None = None
    alt_agl_m: float | None = None
    hfov_deg: float | None = None
    focal_mm: float | None = None
    sensor_w_mm: float | None = None
    heading_deg: float | None = None
    heading_tol_deg: float | None = None
    no_priors: bool = False  # drop every prior of the file (CSV and EXIF) before the flags apply
    from_truth: bool = False  # start from the set's truth (Query.truth_gsd_m / truth_heading_deg): benchmarks
    perturb_seed: int | None = None  # then add the "rough" noise, deterministic per query name and seed

    def __post_init__(self):
        for name, flag in _FLAGS.items():
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, parse_value(name, v, flag, flag))
        if self.no_priors and self.from_truth:
            raise AerolocError("--no-priors and --priors-from-truth exclude each other")
        if self.perturb_seed is not None:
            if isinstance(self.perturb_seed, bool):
                raise AerolocError(f"--perturb-priors {self.perturb_seed!r} is not an integer seed")
            try:
                seed = int(str(self.perturb_seed).strip())
            except ValueError:
                raise AerolocError(f"--perturb-priors {self.perturb_seed!r} is not an integer seed") from None
            object.__setattr__(self, "perturb_seed", seed)

    def values(self) -> dict[str, float]:
        """The fields the flags set."""
        return {k: getattr(self, k) for k in _FLAGS if getattr(self, k) is not None}

    @property
    def empty(self) -> bool:
        return not (self.values() or self.no_priors or self.from_truth or self.perturb_seed is not None)


class _HasPriors(Protocol):  # what apply_overrides needs of a query (aeroloc.core.queries.Query)
    name: str
    priors: Priors
    truth_gsd_m: float | None
    truth_heading_deg: float | None
    origin: str


Q = TypeVar("Q", bound=_HasPriors)


def apply_overrides(queries: Iterable[Q], overrides: PriorOverrides) -> list[Q]:
    """Copies of ``queries`` (:class:`aeroloc.core.queries.Query`) with their priors as the command line says
    (module docstring, "Command-line overrides"). Pure: the queries given are not changed."""
    if overrides.empty:
        return list(queries)
    flags = overrides.values()
    out = []
    for q in queries:
        p = q.priors
        if overrides.no_priors:
            values, sources = {}, {}
        elif overrides.from_truth:
            t = truth_priors(
                q.truth_gsd_m,
                q.truth_heading_deg,
                width_px=p.width_px,
                tolerances={k: getattr(p, k) for k in TOL_FIELDS if p.source(k)},
            )
            values, sources = t.inputs(), dict(t.sources)
        else:
            values, sources = p.inputs(), dict(p.sources)
        if "gsd_m" in flags:  # --gsd restates the ground resolution: none of the file's ways to it count
            drop = GSD_FIELDS
        elif any(k in flags for k in CAMERA_FIELDS):  # a camera flag: the file's given gsd_m no longer holds
            drop = ("gsd_m",)
        else:
            drop = ()
        for k in drop:
            values.pop(k, None)
            sources.pop(k, None)
        values.update(flags)
        sources.update({k: _FLAGS[k] for k in flags})
        new = build_priors(values, sources, width_px=p.width_px, where=q.origin or q.name)
        if overrides.perturb_seed is not None:
            new = new.perturbed(overrides.perturb_seed, q.name)
        out.append(replace(q, priors=new))
    return out


def describe_priors(queries: Iterable[_HasPriors]) -> str:
    """One line for the CLI: how many queries have which prior, and from where."""
    qs = list(queries)
    parts = []
    for what, attr, src in (("ground resolution", "gsd_m", "gsd_source"), ("heading", "heading_deg", "heading_source")):
        have = [q.priors for q in qs if getattr(q.priors, attr) is not None]
        if have:
            origins = sorted({getattr(p, src) or "?" for p in have})
            more = f", +{len(origins) - 2} more" if len(origins) > 2 else ""
            parts.append(f"{what} for {len(have)}/{len(qs)} ({', '.join(origins[:2])}{more})")
        else:
            parts.append(f"no {what}")
    return "priors: " + "; ".join(parts)
