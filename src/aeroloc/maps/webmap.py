"""Self-contained web-map pieces: Leaflet inlined from the ``xstatic-leaflet`` package (its icons as data URIs),
images as data URIs, and a map as a Web Mercator image overlay with its lat/lon bounds, so an HTML page shows
the map imagery offline and exactly under lat/lon points whatever the map's own CRS. Used by the benchmark
report (aeroloc.bench.report) and the flight track page (aeroloc.flight.html)."""

from __future__ import annotations

import base64
import io
import math
import re
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError


# --- vendored Leaflet ---------------------------------------------------------------------------------------
def leaflet_assets() -> tuple[str, str]:
    """(leaflet.js, leaflet.css) from the xstatic-leaflet package, CSS images inlined as data URIs."""
    try:
        import xstatic.pkg.leaflet as xl
    except ImportError:
        raise AerolocError(
            "the HTML report needs Leaflet from the 'xstatic-leaflet' package: pip install xstatic-leaflet"
        ) from None
    base = Path(xl.BASE_DIR)
    js = (base / "leaflet.js").read_text(encoding="utf-8")
    js = re.sub(r"//# sourceMappingURL=\S+\s*$", "", js)
    css = (base / "leaflet.css").read_text(encoding="utf-8")

    def inline(m):
        f = base / m.group(1)
        if not f.is_file():
            return "url()"
        return f"url(data:image/png;base64,{base64.b64encode(f.read_bytes()).decode()})"

    css = re.sub(r"url\((images/[^)]+)\)", inline, css)
    return js, css


# --- images -------------------------------------------------------------------------------------------------
def png_data_uri(path_or_bytes) -> str:
    data = path_or_bytes if isinstance(path_or_bytes, bytes) else Path(path_or_bytes).read_bytes()
    return "data:image/png;base64," + base64.b64encode(data).decode()


def jpeg_data_uri(rgb: np.ndarray, max_side: int, quality: int = 82) -> str:
    from PIL import Image

    im = Image.fromarray(rgb)
    im.thumbnail((max_side, max_side), Image.LANCZOS)
    buf = io.BytesIO()
    im.convert("RGB").save(buf, "JPEG", quality=quality, optimize=True)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode()


def rgba_data_uri(rgba: np.ndarray) -> str:
    """Lossy WebP with alpha (~15x smaller than PNG for aerial imagery; every current browser shows it),
    PNG when this Pillow lacks WebP."""
    from PIL import Image, features

    buf = io.BytesIO()
    im = Image.fromarray(rgba, "RGBA")
    if features.check("webp"):
        im.save(buf, "WEBP", quality=82, method=4)
        return "data:image/webp;base64," + base64.b64encode(buf.getvalue()).decode()
    im.save(buf, "PNG", optimize=True)
    return png_data_uri(buf.getvalue())


def downscaled(m, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """RGB averaged over the valid pixels of each factor x factor block, and the block's validity (> 1/3 valid),
    read in strips so RAM stays bounded on large maps. The output covers ceil(size / factor) blocks: a partial
    last block is padded with invalid pixels, so the georeference (scale = factor) stays exact."""
    import cv2

    w, h = -(-m.width // factor), -(-m.height // factor)
    rgb = np.zeros((h, w, 3), np.uint8)
    valid = np.zeros((h, w), bool)
    block = max(1, 512 // factor)
    for r0 in range(0, h, block):
        rows = min(block, h - r0)
        src_rows = min(rows * factor, m.height - r0 * factor)
        strip, ok = m.read(0, r0 * factor, m.width, src_rows)
        if factor == 1:
            rgb[r0 : r0 + rows], valid[r0 : r0 + rows] = strip, ok
            continue
        pad = np.zeros((rows * factor, w * factor, 3), np.float32)
        wt = np.zeros((rows * factor, w * factor), np.float32)
        pad[:src_rows, : m.width] = strip * ok[..., None]
        wt[:src_rows, : m.width] = ok
        area = (w, rows)
        s_rgb = cv2.resize(pad, area, interpolation=cv2.INTER_AREA)
        s_wt = cv2.resize(wt, area, interpolation=cv2.INTER_AREA)
        rgb[r0 : r0 + rows] = np.clip(s_rgb / np.maximum(s_wt, 1e-6)[..., None], 0, 255).round().astype(np.uint8)
        valid[r0 : r0 + rows] = s_wt > 1 / 3
    return rgb, valid


def map_overlay(map_path, max_px: int = 1400) -> dict:
    """The map as a Web Mercator RGBA PNG data URI with its lat/lon bounds, and the map outline."""
    import rasterio.warp
    from affine import Affine
    from rasterio.transform import array_bounds

    from aeroloc.core import geo
    from aeroloc.maps.sources import open_map

    m = open_map(map_path)
    factor = max(1, math.ceil(max(m.width, m.height) / max_px))
    rgb, valid = downscaled(m, factor)
    h, w = valid.shape
    t = m.transform
    src_t = Affine(t.a * factor, t.b * factor, t.c, t.d * factor, t.e * factor, t.f)
    src = np.concatenate([rgb.transpose(2, 0, 1), (valid * 255).astype(np.uint8)[None]], 0)
    crs = m.crs if not str(m.crs).isdigit() else f"EPSG:{m.crs}"
    west, south, east, north = array_bounds(h, w, src_t)
    dst_t, dw, dh = rasterio.warp.calculate_default_transform(crs, "EPSG:3857", w, h, west, south, east, north)
    dst = np.zeros((4, dh, dw), np.uint8)
    rasterio.warp.reproject(
        src,
        dst,
        src_transform=src_t,
        src_crs=crs,
        dst_transform=dst_t,
        dst_crs="EPSG:3857",
        resampling=rasterio.warp.Resampling.bilinear,
    )
    dst[3] = np.where(dst[3] > 127, 255, 0)
    url = rgba_data_uri(dst.transpose(1, 2, 0))
    lat, lon = geo.latlon_from_mercator([dst_t.c, dst_t.c + dst_t.a * dw], [dst_t.f, dst_t.f + dst_t.e * dh])
    clat, clon = m.pixel_to_latlon([0, m.width, m.width, 0], [0, 0, m.height, m.height])
    return {
        "url": url,
        "bounds": [[float(min(lat)), float(min(lon))], [float(max(lat)), float(max(lon))]],
        "outline": [[float(a), float(b)] for a, b in zip(clat, clon)],
        "name": Path(map_path).name,
    }
