"""Import a local orthophoto (GeoTIFF/COG/any GDAL raster, any CRS) as a map folder: ``MAPDIR/map.tif`` as a
tiled, lossless (DEFLATE) Cloud-Optimized GeoTIFF, optionally warped to Web Mercator, + ``manifest.json``
(layout "geotiff"). The same pipeline then runs on local imagery as on downloaded tiles."""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_path, atomic_write_text

MAP_FILE = "map.tif"


def _open_checked(src: Path):
    import rasterio
    from rasterio.errors import RasterioIOError

    if not src.is_file():
        raise AerolocError(f"{src}: orthophoto not found")
    try:
        ds = rasterio.open(src)
    except RasterioIOError as exc:
        raise AerolocError(f"{src}: not a readable raster ({str(exc)[:120]})") from None
    if ds.crs is None:
        ds.close()
        raise AerolocError(
            f"{src}: the raster has no coordinate reference system (georeference it first, "
            "e.g. gdal_translate -a_srs / gdalwarp)"
        )
    if ds.transform.is_identity:
        ds.close()
        raise AerolocError(f"{src}: the raster has no georeference (identity transform)")
    return ds


def import_orthophoto(src, out, to_webmercator: bool = False, resampling: str = "bilinear") -> dict:
    """Write ``out/map.tif`` (COG) and ``out/manifest.json``; returns the manifest."""
    import rasterio
    import rasterio.shutil
    from rasterio.enums import Resampling
    from rasterio.vrt import WarpedVRT

    from aeroloc.core import geo

    src, out = Path(src), Path(out)
    try:
        method = Resampling[resampling]
    except KeyError:
        raise AerolocError(f"resampling {resampling!r}: use nearest, bilinear, cubic or lanczos") from None
    out.mkdir(parents=True, exist_ok=True)
    dest = out / MAP_FILE
    options = {"driver": "COG", "compress": "DEFLATE", "blocksize": 256, "overviews": "AUTO", "BIGTIFF": "IF_SAFER"}
    with _open_checked(src) as ds:
        source_crs = geo.parse_crs(ds.crs).to_string()
        has_mask = ds.count in (2, 4) or ds.nodata is not None
        with atomic_path(dest) as tmp:  # renamed into place only when complete
            if to_webmercator:
                with WarpedVRT(ds, crs=geo.WEB_MERCATOR, resampling=method, add_alpha=not has_mask) as vrt:
                    rasterio.shutil.copy(vrt, tmp, **options)
            else:
                rasterio.shutil.copy(ds, tmp, **options)
    from aeroloc.maps.sources import GeoTiffMap

    m = GeoTiffMap(dest)
    manifest = {
        "layout": "geotiff",
        "file": MAP_FILE,
        "source": str(src.resolve()),
        "source_crs": source_crs,
        "crs": m.crs,
        "reprojected": bool(to_webmercator),
        "width": m.width,
        "height": m.height,
        "transform": list(m.transform)[:6],
        "bounds": list(m.bounds_latlon()),
        "resolution_m": round(m.resolution_m, 4),
        "created": _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat(),
    }
    atomic_write_text(out / "manifest.json", json.dumps(manifest, indent=1) + "\n")
    return manifest
