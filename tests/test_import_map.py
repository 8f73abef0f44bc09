"""`aeroloc import`: a real orthophoto becomes a map folder (COG + manifest) that aeroloc.maps.sources opens with the same
pixels and georeference; reprojection to Web Mercator keeps every ground point on the same content; bad
input is a one-line error."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from PIL import Image

from aeroloc import cli
from aeroloc.core.errors import AerolocError
from aeroloc.core.geo import crs_to_latlon, geodesic_distance
from aeroloc.maps.orthophoto import import_orthophoto
from aeroloc.maps.sources import open_map


def test_import_keeps_pixels_and_georeference(tmp_path, toledo_map):
    info = import_orthophoto(toledo_map, tmp_path / "m")
    assert info["layout"] == "geotiff" and info["source_crs"] == "EPSG:32617" and not info["reprojected"]
    with rasterio.open(toledo_map) as src, rasterio.open(tmp_path / "m" / "map.tif") as dst:
        assert dst.crs == src.crs and dst.transform == src.transform
        assert np.array_equal(dst.read(), src.read())  # lossless
        assert dst.profile["tiled"] and dst.profile["blockxsize"] == 256 and dst.overviews(1)
        lat, lon = crs_to_latlon([src.bounds.left, src.bounds.right], [src.bounds.top, src.bounds.bottom], src.crs)
    m = open_map(tmp_path / "m")  # through manifest.json
    assert (m.width, m.height) == (708, 801) and m.resolution_m == pytest.approx(0.5, abs=0.01)
    s, w, n, e = json.loads((tmp_path / "m" / "manifest.json").read_text())["bounds"]
    assert n >= max(lat) - 1e-9 and s <= min(lat) + 1e-9 and w <= min(lon) + 1e-9 and e >= max(lon) - 1e-9


def test_import_to_webmercator_keeps_ground_content(tmp_path, naip_map):
    info = import_orthophoto(naip_map, tmp_path / "m", to_webmercator=True)
    assert info["crs"] == "EPSG:3857" and info["source_crs"] == "EPSG:26914" and info["reprojected"]
    src_map, dst_map = open_map(naip_map), open_map(tmp_path / "m")
    # a grid of ground points inside the map: the same lat/lon must show the same pixels in both
    cols, rows = np.meshgrid(np.arange(100, 834, 37) + 0.5, np.arange(100, 623, 31) + 0.5)
    lat, lon = src_map.pixel_to_latlon(cols.ravel(), rows.ravel())
    c2, r2 = dst_map.latlon_to_pixel(lat, lon)
    lat_back, lon_back = dst_map.pixel_to_latlon(c2, r2)
    assert np.max(geodesic_distance(lat, lon, lat_back, lon_back)) < 1e-3
    src_rgb, _ = src_map.read(0, 0, src_map.width, src_map.height)
    dst_rgb, valid = dst_map.read(0, 0, dst_map.width, dst_map.height)
    a = src_rgb[rows.ravel().astype(int), cols.ravel().astype(int)].astype(float)
    b = dst_rgb[r2.astype(int), c2.astype(int)].astype(float)
    shifted = dst_rgb[r2.astype(int) + 6, c2.astype(int) + 6].astype(float)  # ~40 m off: must differ clearly
    err, err_shift = np.median(np.abs(a - b)), np.median(np.abs(a - shifted))
    assert err < 6 and err_shift > 2.5 * err
    # UTM -> Web Mercator turns the frame slightly: the corner wedges outside the source are masked, not data
    assert valid[r2.astype(int), c2.astype(int)].all() and 0.98 < valid.mean() < 1
    assert not (valid[0, 0] or valid[0, -1] or valid[-1, 0] or valid[-1, -1])


def test_cli_import_and_bad_inputs(tmp_path, naip_map, capsys):
    assert cli.main(["import", str(naip_map), "--out", str(tmp_path / "ok")]) == 0
    assert "EPSG:26914" in capsys.readouterr().out
    text = tmp_path / "notes.tif"
    text.write_text("not a raster")
    no_crs = tmp_path / "plain.png"
    Image.fromarray(np.full((32, 32, 3), 120, np.uint8)).save(no_crs)
    for bad, match in [
        (tmp_path / "missing.tif", "not found"),
        (text, "not a readable raster"),
        (no_crs, "no coordinate reference system"),
    ]:
        with pytest.raises(AerolocError, match=match):
            import_orthophoto(bad, tmp_path / "out")
        assert cli.main(["import", str(bad), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert str(bad) in err and len(err.strip().splitlines()) == 1
    assert not list((tmp_path / "out").glob("*.part"))
