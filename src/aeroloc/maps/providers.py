"""Where map tiles come from and which tiles cover an area: XYZ URL templates (also xyzservices names) and
the Google Static Maps API, with exact Web Mercator grids.

Geometry conventions (shared with aeroloc.core.geo): global pixels at zoom z run 0..256*2**z, x east, y south;
a tile's corners are the OUTER edges of its pixels. Bounding boxes are (south, west, north, east) degrees.

Keys never appear in a template as text: templates carry a ``{key}`` placeholder that is filled only when a
request is sent (see :func:`request_url`), so anything printed or saved from a provider is key-free.
"""

from __future__ import annotations

import math
import os
import string
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, urlencode

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError

BBox = tuple[float, float, float, float]  # south, west, north, east (degrees)

GOOGLE_STATIC_URL = "https://maps.googleapis.com/maps/api/staticmap"
GOOGLE_KEY_ENV = "AEROLOC_GOOGLE_KEY"
TILE_KEY_ENV = "AEROLOC_TILE_KEY"
TEMPLATE_FIELDS = {"z", "x", "y", "s", "q", "r", "key"}


# --- areas -------------------------------------------------------------------------------------------------
def check_bbox(bbox) -> BBox:
    """Validate (south, west, north, east); Web Mercator stops at ±85.05°, the antimeridian is not crossed."""
    try:
        south, west, north, east = (float(v) for v in bbox)
    except (TypeError, ValueError):
        raise AerolocError(f"bounding box {bbox!r}: expected four numbers SOUTH WEST NORTH EAST") from None
    if not all(math.isfinite(v) for v in (south, west, north, east)):
        raise AerolocError(f"bounding box {bbox!r}: values must be finite")
    lim = geo.MAX_MERCATOR_LAT
    if not (-lim <= south < north <= lim):
        raise AerolocError(
            f"bounding box {bbox!r}: need -{lim:.2f} <= SOUTH < NORTH <= {lim:.2f} "
            "(is it lon-first? the order is SOUTH WEST NORTH EAST)"
        )
    if not (-180 <= west < east <= 180):
        raise AerolocError(
            f"bounding box {bbox!r}: need -180 <= WEST < EAST <= 180 (crossing the antimeridian "
            "is not supported: download the two halves into two folders)"
        )
    return south, west, north, east


def bbox_around(latlons, margin_m: float) -> BBox:
    """Smallest box holding every (lat, lon) pushed ``margin_m`` metres north, south, east and west."""
    import numpy as np

    pts = [(float(a), float(b)) for a, b in latlons if math.isfinite(a) and math.isfinite(b)]
    if not pts:
        raise AerolocError("no positions to cover (the query file has no lat/lon values)")
    if not margin_m >= 0:
        raise AerolocError(f"margin {margin_m} m: must be >= 0")
    lat, lon = np.array(pts).T
    lats, lons = [lat], [lon]
    for east, north in ((margin_m, 0), (-margin_m, 0), (0, margin_m), (0, -margin_m)):
        # full arrays: geo.offset_latlon does not broadcast scalar offsets over point arrays
        a, b = geo.offset_latlon(lat, lon, np.full_like(lat, east), np.full_like(lat, north))
        lats.append(np.atleast_1d(a))
        lons.append(np.atleast_1d(b))
    lat_all, lon_all = np.concatenate(lats), np.concatenate(lons)
    lim = geo.MAX_MERCATOR_LAT
    return check_bbox(
        (max(-lim, float(lat_all.min())), float(lon_all.min()), min(lim, float(lat_all.max())), float(lon_all.max()))
    )


def _pixel_span(bbox: BBox, zoom: int) -> tuple[float, float, float, float]:
    """(left, top, right, bottom) global pixels of a box at ``zoom``."""
    south, west, north, east = bbox
    left, top = geo.latlon_to_global_px(north, west, zoom)
    right, bottom = geo.latlon_to_global_px(south, east, zoom)
    return float(left), float(top), float(right), float(bottom)


def _check_zoom(zoom: int, max_zoom: int) -> int:
    if not isinstance(zoom, int) or not 0 <= zoom <= max_zoom:
        raise AerolocError(f"zoom {zoom!r}: must be an integer in 0..{max_zoom}")
    return zoom


# --- XYZ grid ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class XYZGrid:
    """The inclusive tile range [x0, x1] x [y0, y1] at ``zoom`` that covers a box."""

    zoom: int
    x0: int
    x1: int
    y0: int
    y1: int

    @property
    def n_tiles(self) -> int:
        return (self.x1 - self.x0 + 1) * (self.y1 - self.y0 + 1)

    def tiles(self):
        """(x, y) row by row, north to south, west to east."""
        for y in range(self.y0, self.y1 + 1):
            for x in range(self.x0, self.x1 + 1):
                yield x, y

    def bounds(self) -> BBox:
        """(south, west, north, east) outer edges of the whole range."""
        north, west, _, _ = geo.xyz_tile_bounds(self.zoom, self.x0, self.y0)
        _, _, south, east = geo.xyz_tile_bounds(self.zoom, self.x1, self.y1)
        return south, west, north, east


def xyz_grid(bbox, zoom: int) -> XYZGrid:
    """Tiles touching the inside of ``bbox``; a box edge that falls exactly on a tile edge adds no extra tile."""
    bbox = check_bbox(bbox)
    zoom = _check_zoom(zoom, 24)
    left, top, right, bottom = (v / 256 for v in _pixel_span(bbox, zoom))
    n = 2**zoom

    def first(v):
        return min(n - 1, max(0, math.floor(v)))

    def last(v):  # the tile holding the point just before v
        return min(n - 1, max(0, math.ceil(v) - 1))

    return XYZGrid(zoom, first(left), max(first(left), last(right)), first(top), max(first(top), last(bottom)))


# --- Google Static Maps grid -------------------------------------------------------------------------------
@dataclass(frozen=True)
class GoogleCell:
    row: int
    col: int
    filename: str
    centre_lat: float
    centre_lon: float
    corners: tuple[float, float, float, float]  # top_left_lat, top_left_lon, bottom_right_lat, bottom_right_lon


@dataclass(frozen=True)
class GoogleGrid:
    """Static Maps images laid edge to edge on the global pixel grid of the *rendered* zoom (zoom + log2 scale).

    Every image is ``size*scale`` px square; the bottom ``crop_px`` rows (the logo strip) are cut, so images
    step ``size*scale`` px east and ``size*scale - crop_px`` px south. The centre of each request sits on an
    integer rendered pixel, so a server that snaps centres to pixels changes nothing, and the corners of
    neighbours are computed from the same integers: edges are shared exactly.
    """

    zoom: int
    scale: int
    size: int
    crop_px: int
    left: int  # global px of the grid's outer top-left corner at the rendered zoom
    top: int
    n_rows: int
    n_cols: int

    @property
    def render_zoom(self) -> int:
        return self.zoom + int(math.log2(self.scale))

    @property
    def image_px(self) -> int:
        return self.size * self.scale

    @property
    def tile_w(self) -> int:
        return self.image_px

    @property
    def tile_h(self) -> int:
        return self.image_px - self.crop_px

    @property
    def n_tiles(self) -> int:
        return self.n_rows * self.n_cols

    def cell(self, row: int, col: int) -> GoogleCell:
        zr, half = self.render_zoom, self.image_px // 2
        x0, y0 = self.left + col * self.tile_w, self.top + row * self.tile_h
        clat, clon = geo.global_px_to_latlon(x0 + half, y0 + half, zr)
        tl_lat, tl_lon = geo.global_px_to_latlon(x0, y0, zr)
        br_lat, br_lon = geo.global_px_to_latlon(x0 + self.tile_w, y0 + self.tile_h, zr)
        return GoogleCell(
            row,
            col,
            f"tile_{row:04d}_{col:04d}.png",
            float(clat),
            float(clon),
            (float(tl_lat), float(tl_lon), float(br_lat), float(br_lon)),
        )

    def cells(self):
        """Row-major: north row first, west to east (the order of map_metadata.txt)."""
        for r in range(self.n_rows):
            for c in range(self.n_cols):
                yield self.cell(r, c)

    def bounds(self) -> BBox:
        first, last = self.cell(0, 0), self.cell(self.n_rows - 1, self.n_cols - 1)
        return last.corners[2], first.corners[1], first.corners[0], last.corners[3]


def google_grid(bbox, zoom: int, size: int = 640, scale: int = 2, crop_px: int = 50) -> GoogleGrid:
    """The fewest Static Maps images (``size`` px at ``scale``) covering ``bbox`` with the logo strip cut."""
    bbox = check_bbox(bbox)
    zoom = _check_zoom(zoom, 21)
    if scale not in (1, 2, 4):
        raise AerolocError(f"Static Maps scale {scale}: must be 1, 2 or 4")
    if not 64 <= size <= 640:
        raise AerolocError(f"Static Maps size {size}: must be in 64..640 px")
    if not 0 <= crop_px < size * scale // 2:
        raise AerolocError(f"logo crop {crop_px} px: must be in 0..{size * scale // 2 - 1}")
    zr = zoom + int(math.log2(scale))
    left, top, right, bottom = _pixel_span(bbox, zr)
    x0, y0 = math.floor(left), math.floor(top)
    w, h = size * scale, size * scale - crop_px
    n_cols = max(1, math.ceil((right - x0) / w))
    n_rows = max(1, math.ceil((bottom - y0) / h))
    return GoogleGrid(zoom, scale, size, crop_px, x0, y0, n_rows, n_cols)


# --- providers ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class XYZProvider:
    """A tile server addressed by a URL template with {z} {x} {y} and optionally {s} {q} {r} {key}."""

    name: str  # display name: an xyzservices name, or the template itself (it holds no key, only {key})
    template: str
    subdomains: tuple[str, ...] = ("a", "b", "c")
    attribution: str = ""
    retina: bool = False
    max_zoom: int | None = None

    @property
    def needs_key(self) -> bool:
        return "{key}" in self.template

    @property
    def tile_size(self) -> int:
        return 512 if self.retina and "{r}" in self.template else 256

    @property
    def suffix(self) -> str | None:
        """Extension the template promises (.png/.jpg/.webp), if any."""
        path = self.template.split("?")[0].lower()
        for ext in (".png", ".jpg", ".jpeg", ".webp"):
            if path.endswith(ext):
                return ".jpg" if ext == ".jpeg" else ext
        return None

    def url(self, z: int, x: int, y: int, key: str | None = None) -> str:
        values = {
            "z": z,
            "x": x,
            "y": y,
            "q": geo.quadkey(x, y, z),
            "r": "@2x" if self.retina else "",
            "s": self.subdomains[(x + y) % len(self.subdomains)] if self.subdomains else "",
        }
        if self.needs_key:
            if not key:
                raise AerolocError(f"provider {self.name} needs a key: set ${TILE_KEY_ENV} or use --key-file")
            values["key"] = quote(key, safe="-_.~")
        return self.template.format(**values)


@dataclass(frozen=True)
class GoogleStaticProvider:
    """The Google Static Maps API (needs a key; satellite imagery by default, lossless PNG32)."""

    base_url: str = GOOGLE_STATIC_URL
    maptype: str = "satellite"
    size: int = 640
    scale: int = 2
    crop_px: int = 50  # logo/copyright strip at the bottom of a scale-2 image
    image_format: str = "png32"
    name: str = "google-static"
    attribution: str = "Imagery (C) Google and its data providers"
    needs_key = True

    def url(self, cell: GoogleCell, zoom: int, key: str | None) -> str:
        if not key:
            raise AerolocError(f"the Google Static Maps API needs a key: set ${GOOGLE_KEY_ENV} or use --key-file")
        query = {
            "center": f"{cell.centre_lat:.10f},{cell.centre_lon:.10f}",
            "zoom": zoom,
            "size": f"{self.size}x{self.size}",
            "scale": self.scale,
            "maptype": self.maptype,
            "format": self.image_format,
            "key": key,
        }
        return f"{self.base_url}?{urlencode(query)}"


def check_template(template: str) -> str:
    try:
        fields = {f for _, f, _, _ in string.Formatter().parse(template) if f is not None}
    except ValueError as exc:
        raise AerolocError(f"tile URL template {template!r}: {exc}") from None
    unknown = fields - TEMPLATE_FIELDS
    if unknown:
        raise AerolocError(
            f"tile URL template {template!r}: unknown placeholder(s) "
            f"{', '.join('{' + f + '}' for f in sorted(unknown))} (known: {{z}} {{x}} {{y}} "
            "{s} {q} {r} {key})"
        )
    if not ({"z", "x", "y"} <= fields or "q" in fields):
        raise AerolocError(f"tile URL template {template!r}: needs {{z}}, {{x}} and {{y}} (or a {{q}} quadkey)")
    return template


def resolve_provider(spec: str, retina: bool = False, google_url: str | None = None):
    """``spec`` is ``google``, an xyzservices name (``Esri.WorldImagery``) or an XYZ URL template."""
    spec = (spec or "").strip()
    if not spec:
        raise AerolocError("no provider given (an XYZ URL template, an xyzservices name or 'google')")
    if spec.lower() in ("google", "google-static", "googlestatic"):
        return GoogleStaticProvider(base_url=google_url or GOOGLE_STATIC_URL)
    if "://" in spec:
        return XYZProvider(name=spec, template=check_template(spec), retina=retina)
    return _xyzservices_provider(spec, retina)


def _xyzservices_provider(name: str, retina: bool) -> XYZProvider:
    import xyzservices.providers as catalogue

    try:
        p = catalogue.query_name(name)
    except ValueError:
        raise AerolocError(
            f"unknown provider {name!r}: give an XYZ URL template, 'google' or an xyzservices "
            "name such as Esri.WorldImagery"
        ) from None
    if not hasattr(p, "build_url"):
        raise AerolocError(
            f"provider {name!r} is a family, not one layer: pick one of {', '.join(sorted(p.flatten()))[:300]}"
        )
    tokens = {k: "{key}" for k, v in p.items() if isinstance(v, str) and v.startswith("<insert your")}
    template = p.build_url(scale_factor="{r}", fill_subdomain=False, **tokens)
    subdomains = p.get("subdomains", "abc")
    return XYZProvider(
        name=p.name,
        template=check_template(template),
        subdomains=tuple(subdomains),
        attribution=p.get("attribution", ""),
        retina=retina,
        max_zoom=p.get("max_zoom"),
    )


def read_key(provider, key_file: str | os.PathLike | None = None) -> str | None:
    """The provider's key from ``key_file`` or the environment; never from the command line."""
    if not getattr(provider, "needs_key", False):
        return None
    if key_file:
        path = Path(key_file)
        if not path.is_file():
            raise AerolocError(f"{path}: key file not found")
        key = path.read_text().strip()
        if not key or len(key.split()) != 1:
            raise AerolocError(f"{path}: key file must hold the key alone on one line")
        return key
    env = GOOGLE_KEY_ENV if isinstance(provider, GoogleStaticProvider) else TILE_KEY_ENV
    key = os.environ.get(env, "").strip()
    if not key:
        raise AerolocError(f"provider {provider.name} needs a key: set ${env} or pass --key-file FILE")
    return key


def redact(text: str, secret: str | None) -> str:
    """``text`` with the secret (raw or URL-encoded) replaced by ***."""
    text = str(text)
    if secret:
        for form in {secret, quote(secret, safe=""), quote(secret, safe="-_.~"), quote(secret)}:
            text = text.replace(form, "***")
    return text
