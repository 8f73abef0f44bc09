"""Map download against a real HTTP server on loopback (pytest-httpserver, threaded) serving real tiles: the NAIP
map reprojected here to the Web Mercator XYZ grid (rasterio.warp) and cut into 256 px PNGs, or rendered as
Google-Static-Maps-like 1280 px images with a logo strip. The server injects the faults real servers produce
(429 + Retry-After, 500/503 bursts, HTML pages with 200, truncated images, dropped connections, responses
slower than the timeout, 404, 403); the client is crashed and killed mid-download and resumed. Every run must
end with files byte-identical to the server's tiles (= a fault-free download), no partial file, and no key in
any message. Web Mercator maths is checked against corners computed by hand from the slippy-map formulas."""

from __future__ import annotations

import io
import json
import math
import re
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from _mapfolders import latlon_to_merc, xyz_bounds
from aeroloc import cli
from aeroloc.core.errors import AerolocError
from aeroloc.maps.download import (
    DownloadReport,
    InvalidImage,
    RetryPolicy,
    TokenBucket,
    decode_image,
    download_map,
    parse_retry_after,
    remove_partial_files,
)
from aeroloc.maps.providers import (
    GoogleStaticProvider,
    XYZProvider,
    bbox_around,
    google_grid,
    read_key,
    redact,
    resolve_provider,
    xyz_grid,
)
from aeroloc.maps.sources import open_map

pytest_httpserver = pytest.importorskip("pytest_httpserver")
from werkzeug import Response  # noqa: E402  (installed with pytest-httpserver)

R = 6378137.0
HALF = math.pi * R
Z = 15  # NAIP (5 m/px) covers 7 x 5 XYZ tiles at zoom 15 (~3.3 m/px on the ground at 47° N)
SECRET = "S3cr3t-Key_abc123"
MAGENTA = (255, 0, 255)


def res_at(zoom: int) -> float:
    """Web Mercator metres per pixel at ``zoom`` (256 px tiles)."""
    return 2 * HALF / (256 * 2**zoom)


def global_px(lat: float, lon: float, zoom: int) -> tuple[float, float]:
    x, y = latlon_to_merc(lat, lon)
    return (x + HALF) / res_at(zoom), (HALF - y) / res_at(zoom)


def naip_latlon_bounds(naip_map) -> tuple[float, float, float, float]:
    import rasterio
    from rasterio.warp import transform_bounds

    with rasterio.open(naip_map) as ds:
        west, south, east, north = transform_bounds(ds.crs, "EPSG:4326", *ds.bounds)
    return south, west, north, east


def warp_naip(naip_map, zoom: int, left_px: int, top_px: int, width: int, height: int) -> np.ndarray:
    """NAIP pixels on the Web Mercator pixel grid of ``zoom`` whose top-left is global pixel (left, top)."""
    import rasterio
    from affine import Affine
    from rasterio.warp import Resampling, reproject

    res = res_at(zoom)
    dst_transform = Affine(res, 0, -HALF + left_px * res, 0, -res, HALF - top_px * res)
    out = np.zeros((3, height, width), np.uint8)
    with rasterio.open(naip_map) as ds:
        reproject(
            ds.read([1, 2, 3]),
            out,
            src_transform=ds.transform,
            src_crs=ds.crs,
            dst_transform=dst_transform,
            dst_crs="EPSG:3857",
            resampling=Resampling.bilinear,
        )
    return np.moveaxis(out, 0, -1).copy()


def png(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


@dataclass
class TileSet:
    zoom: int
    x0: int
    x1: int
    y0: int
    y1: int
    bbox: tuple
    mosaic: np.ndarray
    tiles: dict  # (x, y) -> PNG bytes


@pytest.fixture(scope="module")
def naip_tiles(naip_map) -> TileSet:
    bbox = naip_latlon_bounds(naip_map)
    south, west, north, east = bbox
    # tile range by hand: x = floor(global px / 256) of the west/east edges, y of the north/south edges
    (px_l, px_t), (px_r, px_b) = global_px(north, west, Z), global_px(south, east, Z)
    x0, y0, x1, y1 = int(px_l // 256), int(px_t // 256), int(px_r // 256), int(px_b // 256)
    mosaic = warp_naip(naip_map, Z, x0 * 256, y0 * 256, (x1 - x0 + 1) * 256, (y1 - y0 + 1) * 256)
    tiles = {
        (x, y): png(mosaic[(y - y0) * 256 : (y - y0 + 1) * 256, (x - x0) * 256 : (x - x0 + 1) * 256])
        for y in range(y0, y1 + 1)
        for x in range(x0, x1 + 1)
    }
    return TileSet(Z, x0, x1, y0, y1, bbox, mosaic, tiles)


# the client gives up after TIMEOUT_S; a "slow" tile takes SLOW_S. A clean local response must stay well under
# TIMEOUT_S on a loaded 2-core machine (0.5 s gave a spurious timeout while the suite shared the cores)
SLOW_S, TIMEOUT_S = 3.0, 1.5


@dataclass
class FaultyTileServer:
    """Serves /tiles/{z}/{x}/{y}.png; ``faults[(x, y)]`` lists what the 1st, 2nd … request of a tile gets."""

    tiles: dict
    key: str | None = None
    faults: dict = field(default_factory=dict)
    hits: Counter = field(default_factory=Counter)
    delay_s: float = 0.0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, request):
        m = re.fullmatch(r"/tiles/(\d+)/(\d+)/(\d+)\.png", request.path)
        if not m:
            return Response("no such path", 404)
        if self.key is not None and request.args.get("token") != self.key:
            return Response("<html><body>invalid token</body></html>", 403, content_type="text/html")
        x, y = int(m.group(2)), int(m.group(3))
        with self.lock:
            n = self.hits[(x, y)]
            self.hits[(x, y)] += 1
        plan = self.faults.get((x, y), [])
        fault = plan[n] if n < len(plan) else (plan[-1] if plan and plan[-1].endswith("*") else None)
        fault = fault.rstrip("*") if fault else None
        body = self.tiles.get((x, y))
        if self.delay_s:
            time.sleep(self.delay_s)
        if body is None or fault == "404":
            return Response("not found", 404)
        if fault == "429":
            return Response("Too Many Requests", 429, headers={"Retry-After": "7"})
        if fault in ("500", "502"):
            return Response("<html><h1>Internal Server Error</h1></html>", int(fault), content_type="text/html")
        if fault == "503":
            return Response("busy", 503, headers={"Retry-After": "2"})
        if fault == "html":  # a captive portal / error page served with 200
            return Response(
                "<!DOCTYPE html><html><body>Service temporarily unavailable</body></html>",
                200,
                content_type="text/html",
            )
        if fault == "trunc":  # a complete HTTP response whose image is cut short
            return Response(body[: len(body) // 2], 200, content_type="image/png")
        if fault == "cut":  # the connection drops mid-body (Content-Length promises more)
            return Response(
                iter([body[: len(body) // 3]]),
                200,
                content_type="image/png",
                headers={"Content-Length": str(len(body))},
                direct_passthrough=True,
            )
        if fault == "slow":  # longer than the client's read timeout
            time.sleep(SLOW_S)
        return Response(body, 200, content_type="image/png")


@pytest.fixture(scope="module")
def http_server():
    import logging

    from pytest_httpserver import HTTPServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = HTTPServer(host="127.0.0.1", port=0, threaded=True)
    server.start()
    yield server
    server.clear()
    server.stop()


@pytest.fixture
def tile_server(http_server, naip_tiles):
    handler = FaultyTileServer(naip_tiles.tiles)
    http_server.clear()
    http_server.expect_request(re.compile(r"^/tiles/.*")).respond_with_handler(handler)
    handler.base = http_server.url_for("/tiles")
    return handler


class Sleeps:
    """Injectable sleep: records the delays, waits for none of them."""

    def __init__(self):
        self.calls = []

    def __call__(self, s):
        self.calls.append(s)


def fast_policy(sleeps=None, attempts=6, timeout=TIMEOUT_S) -> RetryPolicy:
    return RetryPolicy(
        attempts=attempts,
        backoff_s=0.01,
        connect_timeout_s=2,
        read_timeout_s=timeout,
        total_timeout_s=5,
        sleep=sleeps or Sleeps(),
    )


def fetch(out, ts: TileSet, server, policy=None, key=None, template=None, workers=4):
    provider = resolve_provider(template or server.base + "/{z}/{x}/{y}.png")  # as the CLI does
    return download_map(
        out,
        ts.bbox,
        ts.zoom,
        provider,
        key=key,
        workers=workers,
        rate=1000,
        policy=policy or fast_policy(),
        progress=False,
    )


def tile_files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*.png"))}


def expected_files(ts: TileSet) -> dict:
    return {f"{ts.zoom}/{x}/{y}.png": b for (x, y), b in ts.tiles.items()}


def partial_files(folder: Path) -> list:
    return [p for p in folder.rglob("*") if p.name.endswith(".part") or p.name.startswith(".")]


# --- Web Mercator grids, by hand ------------------------------------------------------------------------------
def test_xyz_grid_at_zoom_1_splits_at_the_equator_and_greenwich():
    # z=1: four tiles, x=0 west of 0°, y=0 north of 0°
    g = xyz_grid((10, 10, 20, 20), 1)
    assert (g.zoom, g.x0, g.x1, g.y0, g.y1) == (1, 1, 1, 0, 0)
    g = xyz_grid((-10, -10, 10, 10), 1)
    assert (g.x0, g.x1, g.y0, g.y1) == (0, 1, 0, 1)
    # a box whose south/west edges lie exactly on the tile edges (lat 0, lon 0) takes no extra tile
    g = xyz_grid((0, 0, 10, 10), 1)
    assert (g.x0, g.x1, g.y0, g.y1) == (1, 1, 0, 0)
    south, west, north, east = g.bounds()
    assert (south, west, east) == pytest.approx((0, 0, 180), abs=1e-12)
    assert north == pytest.approx(85.0511287798, abs=1e-9)


def test_xyz_grid_at_zoom_10_matches_hand_computed_corners():
    # (47.02 N, 99.15 W) at z=10: x = (−99.15+180)/360·1024 = 229.97 -> 229;
    # y = (1 − ln(tan φ + sec φ)/π)/2·1024 = (1 − 0.932137/π)/2·1024 = 360.08 -> 360.
    # Tile (10, 229, 360): west = 229/1024·360 − 180 = −99.4921875, east = 230/1024·360 − 180 = −99.140625,
    # north = atan(sinh(π(1 − 2·360/1024))) = atan(sinh(0.932660)) = atan(1.073869) = 47.0401821°,
    # south = atan(sinh(π(1 − 2·361/1024))) = 46.8000594°.
    g = xyz_grid((47.0199, -99.1501, 47.0201, -99.1499), 10)
    assert (g.x0, g.x1, g.y0, g.y1) == (229, 229, 360, 360)
    south, west, north, east = g.bounds()
    assert west == pytest.approx(-99.4921875, abs=1e-12) and east == pytest.approx(-99.140625, abs=1e-12)
    assert north == pytest.approx(47.0401821448, abs=1e-9) and south == pytest.approx(46.8000594468, abs=1e-9)


def test_google_grid_centres_on_pixels_and_shares_edges():
    bbox = (47.008, -99.17, 47.033, -99.14)
    g = google_grid(bbox, 15, size=640, scale=2, crop_px=50)
    assert g.render_zoom == 16 and (g.tile_w, g.tile_h) == (1280, 1230)
    (px_l, px_t), (px_r, px_b) = global_px(bbox[2], bbox[1], 16), global_px(bbox[0], bbox[3], 16)
    assert (g.left, g.top) == (math.floor(px_l), math.floor(px_t))  # grid starts on the box's NW pixel
    assert g.left + g.n_cols * 1280 >= px_r and g.top + g.n_rows * 1230 >= px_b  # covers the box …
    assert g.left + (g.n_cols - 1) * 1280 < px_r and g.top + (g.n_rows - 1) * 1230 < px_b  # … with no spare row/column
    cells = {(c.row, c.col): c for c in g.cells()}
    for (row, col), c in cells.items():
        cx, cy = global_px(c.centre_lat, c.centre_lon, 16)  # the request centre is the image's middle pixel edge
        assert cx == pytest.approx(g.left + col * 1280 + 640, abs=1e-6)
        assert cy == pytest.approx(g.top + row * 1230 + 640, abs=1e-6)
        tl_x, tl_y = global_px(c.corners[0], c.corners[1], 16)
        br_x, br_y = global_px(c.corners[2], c.corners[3], 16)  # outer edges: 1280 x 1230 px apart
        assert (br_x - tl_x, br_y - tl_y) == (pytest.approx(1280, abs=1e-6), pytest.approx(1230, abs=1e-6))
        if col:
            assert c.corners[1] == cells[(row, col - 1)].corners[3]  # shared edges, bit for bit
        if row:
            assert c.corners[0] == cells[(row - 1, col)].corners[2]


def test_providers_fill_subdomains_quadkeys_retina_and_keys():
    p = XYZProvider(
        "t", "https://{s}.tiles.example/{z}/{x}/{y}{r}.png?q={q}&k={key}", subdomains=("a", "b"), retina=True
    )
    # Bing's documented example: tile x=3, y=5 at level 3 has quadkey "213"
    url = p.url(3, 3, 5, key="k y/")
    assert url == "https://a.tiles.example/3/3/5@2x.png?q=213&k=k%20y%2F" and p.tile_size == 512
    assert p.url(3, 4, 5, key="k").startswith("https://b.") and p.suffix == ".png"
    with pytest.raises(AerolocError, match="needs a key"):
        p.url(3, 3, 5)
    esri = resolve_provider("Esri.WorldImagery")
    assert esri.template.endswith("/World_Imagery/MapServer/tile/{z}/{y}/{x}") and "Esri" in esri.attribution
    assert esri.url(15, 7355, 11520).endswith("/tile/15/11520/7355") and not esri.needs_key
    tf = resolve_provider("Thunderforest.Landscape")  # a catalogue entry with a token placeholder
    assert tf.needs_key and "{key}" in tf.template and "insert" not in tf.template
    assert isinstance(resolve_provider("google"), GoogleStaticProvider)
    for bad in ("No.Such.Provider", "https://x/{z}/{x}.png", "https://x/{z}/{x}/{y}/{foo}.png", "Esri"):
        with pytest.raises(AerolocError):
            resolve_provider(bad)


def test_bbox_and_zoom_errors_are_clear():
    for bbox, match in [
        ((47, -99, 46, -98), "SOUTH < NORTH"),
        ((-99, 47, -98, 48), "SOUTH < NORTH"),
        ((47, 179, 48, -179), "antimeridian"),
        (("a", 1, 2, 3), "four numbers"),
    ]:
        with pytest.raises(AerolocError, match=match):
            xyz_grid(bbox, 10)
    with pytest.raises(AerolocError, match="zoom"):
        xyz_grid((47, -99, 48, -98), 30)


def test_bbox_around_adds_the_margin_in_metres(naip_dev):
    from aeroloc.core.geo import geodesic_distance
    from aeroloc.core.queries import load_queries

    qs = load_queries(naip_dev, require_images=False)
    lat, lon = np.array([q.lat for q in qs]), np.array([q.lon for q in qs])
    south, west, north, east = bbox_around(zip(lat, lon), 150.0)
    i_n, i_s, i_e, i_w = lat.argmax(), lat.argmin(), lon.argmax(), lon.argmin()
    assert geodesic_distance(lat[i_n], lon[i_n], north, lon[i_n]) == pytest.approx(150, abs=0.01)
    assert geodesic_distance(lat[i_s], lon[i_s], south, lon[i_s]) == pytest.approx(150, abs=0.01)
    assert geodesic_distance(lat[i_e], lon[i_e], lat[i_e], east) == pytest.approx(150, abs=0.05)
    assert geodesic_distance(lat[i_w], lon[i_w], lat[i_w], west) == pytest.approx(150, abs=0.05)
    with pytest.raises(AerolocError, match="no positions"):
        bbox_around([(math.nan, math.nan)], 10)


# --- building blocks ------------------------------------------------------------------------------------------
def test_decode_image_rejects_html_truncated_and_wrong_size(naip_tiles):
    body = next(iter(naip_tiles.tiles.values()))
    im, ext = decode_image(body, (256, 256))
    assert ext == ".png" and im.size == (256, 256)
    for bad, match in [
        (b"<!DOCTYPE html><html></html>", "HTML"),
        (body[: len(body) // 2], "undecodable"),
        (b"", "empty"),
        (b"\x89PNG\r\n\x1a\n garbage", "undecodable"),
    ]:
        with pytest.raises(InvalidImage, match=match) as e:
            decode_image(bad, (256, 256))
        assert e.value.retry
    with pytest.raises(InvalidImage, match="expected 512x512") as e:
        decode_image(body, (512, 512))
    assert not e.value.retry


def test_backoff_grows_with_jitter_and_honours_retry_after():
    import random

    p = RetryPolicy(backoff_s=1.0, max_backoff_s=8.0, rng=random.Random(0))
    for attempt, full in [(1, 1), (2, 2), (3, 4), (4, 8), (6, 8)]:
        delays = [p.delay(attempt) for _ in range(200)]
        assert full / 2 <= min(delays) and max(delays) <= full and np.std(delays) > 0  # jittered, capped
    assert p.delay(1, retry_after=30) == 30 and p.delay(1, retry_after=1e6) == p.max_retry_after_s
    assert parse_retry_after("120") == 120
    assert parse_retry_after("Wed, 21 Oct 2015 07:28:30 GMT", now=1445412480.0) == pytest.approx(30)
    assert parse_retry_after("soon") is None and parse_retry_after(None) is None


def test_token_bucket_paces_requests():
    now = [0.0]

    def sleep(s):
        now[0] += s

    bucket = TokenBucket(rate=10, burst=2, clock=lambda: now[0], sleep=sleep)
    for _ in range(12):
        bucket.acquire()
    assert now[0] == pytest.approx(1.0)  # 2 free (burst), then one every 0.1 s


def test_redact_hides_raw_and_url_encoded_keys():
    assert redact("GET /x?key=a%2Bb%2F and a+b/", "a+b/") == "GET /x?key=*** and ***"


def test_key_comes_from_env_or_file_never_argv(tmp_path, monkeypatch, capsys):
    p = XYZProvider("t", "http://x/{z}/{x}/{y}.png?k={key}")
    monkeypatch.delenv("AEROLOC_TILE_KEY", raising=False)
    with pytest.raises(AerolocError, match="AEROLOC_TILE_KEY"):
        read_key(p)
    monkeypatch.setenv("AEROLOC_TILE_KEY", " envkey\n")
    assert read_key(p) == "envkey"
    (tmp_path / "k").write_text("filekey\n")
    assert read_key(p, tmp_path / "k") == "filekey"
    monkeypatch.setenv("AEROLOC_GOOGLE_KEY", "gkey")
    assert read_key(GoogleStaticProvider()) == "gkey" and read_key(XYZProvider("t", "http://x/{z}/{x}/{y}")) is None
    argv = ["download", "--bbox", "1", "2", "3", "4", "--zoom", "3", "--provider", "x", "--out", "o"]
    for opt in ("--key", "--api-key"):  # keys never go through argv
        with pytest.raises(SystemExit):
            cli.main([*argv, opt, "S3cr3tValue"])
        err = capsys.readouterr().err
        assert "S3cr3tValue" not in err and "not taken from the command line" in err
    with pytest.raises(SystemExit):  # no abbreviations: '--key-f SECRET' is not read as a key file named SECRET
        cli.main([*argv, "--key-f", "S3cr3tValue"])
    assert "unrecognized arguments" in capsys.readouterr().err


# --- downloads against the loopback server -------------------------------------------------------------------
def test_fault_free_download_is_the_server_mosaic(tmp_path, naip_tiles, tile_server):
    ts = naip_tiles
    report, manifest = fetch(tmp_path / "map", ts, tile_server)
    assert report.complete and report.downloaded == len(ts.tiles) == 35 and report.retries == 0
    assert tile_files(tmp_path / "map") == expected_files(ts)  # bytes exactly as served
    assert set(tile_server.hits.values()) == {1}
    assert manifest["layout"] == "xyz" and manifest["zoom"] == Z and manifest["tile_size"] == 256
    assert manifest["x_range"] == [ts.x0, ts.x1] and manifest["y_range"] == [ts.y0, ts.y1]
    assert manifest["tiles_missing"] == [] and manifest["tiles_expected"] == 35 and manifest["ext"] == "png"
    on_disk = json.loads((tmp_path / "map" / "manifest.json").read_text())
    assert on_disk["complete"] and on_disk["bounds"] == manifest["bounds"]
    north, west, _, _ = xyz_bounds(Z, ts.x0, ts.y0)
    _, _, south, east = xyz_bounds(Z, ts.x1, ts.y1)
    assert on_disk["bounds"] == pytest.approx([south, west, north, east], abs=1e-10)
    # the folder opens as a map whose pixels and georeference are the warped NAIP mosaic
    m = open_map(tmp_path / "map")
    rgb, valid = m.read(0, 0, m.width, m.height)
    assert valid.all() and np.array_equal(rgb, ts.mosaic)
    lat, lon = m.pixel_to_latlon(0, 0)
    assert (float(lat), float(lon)) == (pytest.approx(north, abs=1e-9), pytest.approx(west, abs=1e-9))
    assert not partial_files(tmp_path / "map")


def test_every_fault_costs_one_retry_and_the_result_is_byte_identical(tmp_path, naip_tiles, tile_server):
    ts = naip_tiles
    keys = sorted(ts.tiles)
    plan = [
        ["429"],
        ["500", "500", "500"],
        ["503", "502"],
        ["html"],
        ["trunc"],
        ["cut"],
        ["slow"],
        ["429", "html", "cut", "503", "trunc"],
        ["slow", "500"],
        ["cut", "cut"],
    ]
    tile_server.faults = {keys[3 * i]: f for i, f in enumerate(plan)}
    sleeps = Sleeps()
    report, manifest = fetch(tmp_path / "faulty", ts, tile_server, policy=fast_policy(sleeps))
    assert report.complete and manifest["tiles_missing"] == [] and report.failed == {}
    assert tile_files(tmp_path / "faulty") == expected_files(ts)
    n_faults = sum(len(f) for f in plan)
    assert report.retries == n_faults == len(sleeps.calls)
    for k in keys:  # faulted tiles were asked once per fault + once more; clean tiles once
        assert tile_server.hits[k] == len(tile_server.faults.get(k, [])) + 1
    assert sum(1 for s in sleeps.calls if s >= 7) == 2  # Retry-After: 7 on both 429s
    assert sum(1 for s in sleeps.calls if 2 <= s < 7) == 2  # Retry-After: 2 on both 503s
    assert report.retry_reasons["timeout"] == 2 and report.retry_reasons["HTTP 429"] == 2
    assert not partial_files(tmp_path / "faulty")


def test_lasting_failures_are_reported_and_a_rerun_fetches_only_them(
    tmp_path, naip_tiles, tile_server, capsys, monkeypatch
):
    ts = naip_tiles
    keys = sorted(ts.tiles)
    tile_server.faults = {keys[0]: ["500*"], keys[1]: ["404"], keys[2]: ["html*"]}
    out = tmp_path / "map"
    args = [
        "download",
        "--bbox",
        *map(str, ts.bbox),
        "--zoom",
        str(Z),
        "--provider",
        tile_server.base + "/{z}/{x}/{y}.png",
        "--out",
        str(out),
        "--retries",
        "3",
        "--rate",
        "1000",
        "--no-progress",
        "--timeout",
        "2",
    ]
    import aeroloc.maps.download as dl

    monkeypatch.setattr(dl.RetryPolicy, "delay", lambda self, attempt, retry_after=None: 0.0)  # no waiting
    assert cli.main(args) == 1  # tiles missing -> non-zero exit
    text = capsys.readouterr().out
    assert "3 missing of 35" in text and "HTTP 500 (after 3 attempts)" in text and "HTTP 404" in text
    assert "not an image" in text
    assert tile_server.hits[keys[0]] == 3 and tile_server.hits[keys[1]] == 1  # 404 is not retried
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(map(tuple, manifest["tiles_missing"])) == sorted(keys[:3]) and not manifest["complete"]
    assert len(tile_files(out)) == 32 and not partial_files(out)

    tile_server.faults, before = {}, dict(tile_server.hits)
    assert cli.main(args) == 0
    assert {
        k: tile_server.hits[k] - before.get(k, 0) for k in keys if tile_server.hits[k] != before.get(k, 0)
    } == dict.fromkeys(keys[:3], 1)  # only the missing tiles were fetched
    assert tile_files(out) == expected_files(ts)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["complete"] and manifest["tiles_missing"] == []
    assert "32 already present" in capsys.readouterr().out


def test_resume_replaces_a_corrupt_tile(tmp_path, naip_tiles, tile_server):
    ts = naip_tiles
    out = tmp_path / "map"
    fetch(out, ts, tile_server)
    x, y = sorted(ts.tiles)[5]
    bad = out / str(Z) / str(x) / f"{y}.png"
    bad.write_bytes(bad.read_bytes()[:300])  # e.g. a file damaged outside aeroloc
    before = dict(tile_server.hits)
    report, _ = fetch(out, ts, tile_server)
    assert report.downloaded == 1 and report.skipped == 34
    assert tile_server.hits[(x, y)] == before[(x, y)] + 1
    assert tile_files(out) == expected_files(ts)


def test_crash_mid_download_then_resume(tmp_path, naip_tiles, tile_server, monkeypatch):
    import aeroloc.maps.download as dl

    ts = naip_tiles
    out = tmp_path / "map"
    real_write, saved, k, lock = dl.atomic_write_bytes, [], 10, threading.Lock()

    def crashing_write(path, data):
        if Path(path).suffix == ".png":
            with lock:
                if len(saved) == k:
                    raise KeyboardInterrupt  # Ctrl-C while the 11th tile is being written
                saved.append(path)
        real_write(path, data)

    monkeypatch.setattr(dl, "atomic_write_bytes", crashing_write)
    with pytest.raises(KeyboardInterrupt):
        fetch(out, ts, tile_server, workers=2)
    monkeypatch.setattr(dl, "atomic_write_bytes", real_write)
    on_disk = tile_files(out)
    assert len(on_disk) == k and not partial_files(out)
    expected = expected_files(ts)
    assert all(expected[name] == data for name, data in on_disk.items())
    manifest = json.loads((out / "manifest.json").read_text())
    assert not manifest["complete"] and len(manifest["tiles_missing"]) == 35 - k

    before = dict(tile_server.hits)
    report, manifest = fetch(out, ts, tile_server)
    assert report.skipped == k and report.downloaded == 35 - k and manifest["complete"]
    saved_keys = [(int(x), int(y[:-4])) for _, x, y in (name.split("/") for name in on_disk)]
    refetched = [key for key in saved_keys if tile_server.hits[key] != before[key]]
    assert refetched == []  # tiles saved before the crash were not downloaded again
    assert tile_files(out) == expected and not partial_files(out)


def test_killed_process_resumes_to_the_same_map(tmp_path, naip_tiles, tile_server):
    ts = naip_tiles
    out = tmp_path / "map"
    tile_server.delay_s = 0.05
    args = [
        sys.executable,
        "-m",
        "aeroloc.cli",
        "download",
        "--bbox",
        *map(str, ts.bbox),
        "--zoom",
        str(Z),
        "--provider",
        tile_server.base + "/{z}/{x}/{y}.png",
        "--out",
        str(out),
        "--workers",
        "2",
        "--rate",
        "1000",
        "--no-progress",
    ]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while len(list(out.rglob("*.png"))) < 8 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    n_before = len(list(out.rglob("*.png")))
    assert 8 <= n_before < 35, "the download should have been killed half-way"
    (out / str(Z) / str(ts.x0) / ".stale.png.part").write_bytes(b"\x89PNG half")  # what a kill can leave
    tile_server.delay_s = 0.0
    report, manifest = fetch(out, ts, tile_server)
    assert report.skipped >= 8 and manifest["complete"]
    assert tile_files(out) == expected_files(ts) and not partial_files(out)


def test_keys_never_reach_messages_logs_or_manifest(tmp_path, naip_tiles, tile_server, monkeypatch, capsys, caplog):
    import logging

    import aeroloc.maps.download as dl

    ts = naip_tiles
    keys = sorted(ts.tiles)
    tile_server.key = SECRET
    tile_server.faults = {
        keys[0]: ["500*"],
        keys[1]: ["cut*"],
        keys[2]: ["slow*"],
        keys[3]: ["404"],
        keys[4]: ["html*"],
    }
    monkeypatch.setattr(dl.RetryPolicy, "delay", lambda self, attempt, retry_after=None: 0.0)
    monkeypatch.setenv("AEROLOC_TILE_KEY", SECRET)
    template = tile_server.base + "/{z}/{x}/{y}.png?token={key}"
    out = tmp_path / "map"
    args = [
        "download",
        "--bbox",
        *map(str, ts.bbox),
        "--zoom",
        str(Z),
        "--provider",
        template,
        "--out",
        str(out),
        "--retries",
        "2",
        "--timeout",
        str(TIMEOUT_S),
        "--rate",
        "1000",
    ]
    with caplog.at_level(logging.DEBUG):
        assert cli.main(args) == 1
        captured = capsys.readouterr()
    assert "timeout" in captured.out and "truncated body" in captured.out and "HTTP 500" in captured.out
    manifest_text = (out / "manifest.json").read_text()
    assert "{key}" in json.loads(manifest_text)["provider"]  # the template is kept, with its placeholder
    for text in (captured.out, captured.err, caplog.text, manifest_text):
        assert SECRET not in text and SECRET.lower() not in text.lower()
    # a wrong key: the server refuses (403) -> one-line error, exit 2, key not shown
    monkeypatch.setenv("AEROLOC_TILE_KEY", "Wr0ngKey-xyz")
    tile_server.faults = {}
    assert cli.main([*args[:-2], "--rate", "1000", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "HTTP 403" in err and "access refused" in err and "Wr0ngKey" not in err
    assert len(err.strip().splitlines()) == 1


def test_unreachable_server_stops_early_and_says_so(tmp_path, naip_tiles):
    import socket

    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    provider = resolve_provider(f"http://127.0.0.1:{port}/{{z}}/{{x}}/{{y}}.png")
    # one worker: the stop point does not depend on how the two cores are shared (the worker counts its failures
    # in a row itself; when the collecting thread did, a loaded machine let the worker try 9 tiles, not 5)
    report, manifest = download_map(
        tmp_path / "m",
        naip_tiles.bbox,
        Z,
        provider,
        workers=1,
        rate=1000,
        policy=fast_policy(attempts=2),
        progress=False,
        max_consecutive_failures=5,
    )
    assert "in a row failed" in report.aborted and "connection error" in report.aborted
    assert len(report.failed) == 35 and len(manifest["tiles_missing"]) == 35 and report.downloaded == 0
    assert sum(r == "not attempted (run stopped)" for r in report.failed.values()) == 35 - 5


def test_max_tiles_and_foreign_folder_are_refused(tmp_path, naip_tiles, tile_server):
    ts = naip_tiles
    provider = resolve_provider(tile_server.base + "/{z}/{x}/{y}.png")
    with pytest.raises(AerolocError, match="max-tiles"):
        download_map(tmp_path / "a", ts.bbox, 17, provider, max_tiles=100, progress=False)
    fetch(tmp_path / "b", ts, tile_server)
    with pytest.raises(AerolocError, match="another download"):  # same folder, other zoom
        download_map(tmp_path / "b", ts.bbox, 14, provider, progress=False, policy=fast_policy())


def test_download_around_a_flight_covers_every_position(tmp_path, naip_tiles, tile_server, naip_dev, capsys):
    from aeroloc.core.queries import load_queries

    out = tmp_path / "map"
    args = [
        "download",
        "--around",
        str(naip_dev),
        "--margin-m",
        "100",
        "--zoom",
        "13",
        "--provider",
        tile_server.base + "/{z}/{x}/{y}.png",
        "--out",
        str(out),
        "--no-progress",
        "--rate",
        "1000",
    ]
    tile_server.tiles = {}  # zoom 13 is not served: every tile is a 404, but the plan is what we check here
    assert cli.main(args) == 1
    manifest = json.loads((out / "manifest.json").read_text())
    south, west, north, east = manifest["bbox_requested"]
    for q in load_queries(naip_dev, require_images=False):
        assert south < q.lat < north and west < q.lon < east
    s2, w2, n2, e2 = manifest["bounds"]  # whole tiles around the requested box
    assert s2 <= south and w2 <= west and n2 >= north and e2 >= east
    assert "HTTP 404" in capsys.readouterr().out


# --- Google Static Maps ---------------------------------------------------------------------------------------
GOOGLE_BBOX = (47.008, -99.17, 47.033, -99.14)
GOOGLE_ZOOM, RENDER_ZOOM = 15, 16  # scale 2: a 640 px request renders 1280 px at zoom 16


@dataclass
class StaticMapsServer:
    """Renders ``size*scale`` px centred on the requested centre from a world mosaic, logo strip at the bottom."""

    world: np.ndarray
    left: int  # global pixel (zoom 16) of world[0, 0]
    top: int
    key: str
    faults: list = field(default_factory=list)
    requests: int = 0

    def __call__(self, request):
        a = request.args
        if a.get("key") != self.key:
            return Response("The provided API key is invalid.", 403)
        self.requests += 1
        if self.faults:
            fault = self.faults.pop(0)
            if fault == "429":
                return Response("quota", 429, headers={"Retry-After": "5"})
            if fault == "html":
                return Response("<html>error</html>", 200, content_type="text/html")
        if (a.get("size"), a.get("scale"), a.get("maptype")) != ("640x640", "2", "satellite"):
            return Response("unexpected parameters", 400)
        lat, lon = map(float, a["center"].split(","))
        cx, cy = global_px(lat, lon, int(a["zoom"]) + 1)
        if abs(cx - round(cx)) > 1e-3 or abs(cy - round(cy)) > 1e-3:
            return Response("centre is not on the pixel grid", 400)
        c0, r0 = int(round(cx)) - 640 - self.left, int(round(cy)) - 640 - self.top
        img = np.zeros((1280, 1280, 3), np.uint8)
        rs, cs = (
            slice(max(r0, 0), min(r0 + 1280, self.world.shape[0])),
            slice(max(c0, 0), min(c0 + 1280, self.world.shape[1])),
        )
        img[rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0] = self.world[rs, cs]
        img[-50:] = MAGENTA  # the Google logo / copyright strip
        return Response(png(img), 200, content_type="image/png")


def test_google_static_download_mosaics_exactly(tmp_path, naip_map, http_server):
    south, west, north, east = GOOGLE_BBOX
    (px_l, px_t), (px_r, px_b) = global_px(north, west, RENDER_ZOOM), global_px(south, east, RENDER_ZOOM)
    left, top = int(px_l) - 2, int(px_t) - 2
    world = warp_naip(naip_map, RENDER_ZOOM, left, top, int(px_r) - left + 1300, int(px_b) - top + 1300)
    server = StaticMapsServer(world, left, top, SECRET, faults=["429", "html"])
    http_server.clear()
    http_server.expect_request("/staticmap").respond_with_handler(server)
    provider = GoogleStaticProvider(base_url=http_server.url_for("/staticmap"))
    sleeps = Sleeps()
    out = tmp_path / "google"
    report, manifest = download_map(
        out,
        GOOGLE_BBOX,
        GOOGLE_ZOOM,
        provider,
        key=SECRET,
        rate=1000,
        policy=fast_policy(sleeps, timeout=10),
        progress=False,
    )  # renders take time
    assert report.complete and report.retries == 2 and max(sleeps.calls) >= 5
    assert manifest["layout"] == "metadata" and manifest["tile_size"] == [1280, 1230]
    g = manifest["grid"]
    assert (g["rows"], g["cols"]) == (2, 2) and server.requests == 4 + 2
    rows = (out / "map_metadata.txt").read_text().splitlines()
    assert rows[0].split() == ["filename", "top_left_lat", "top_left_lon", "bottom_right_lat", "bottom_right_lon"]
    names = [ln.split()[0] for ln in rows[1:]]
    assert names == ["tile_0000_0000.png", "tile_0000_0001.png", "tile_0001_0000.png", "tile_0001_0001.png"]
    tl_lat, tl_lon = map(float, rows[1].split()[1:3])
    assert global_px(tl_lat, tl_lon, RENDER_ZOOM) == (
        pytest.approx(g["left_px"], abs=1e-4),
        pytest.approx(g["top_px"], abs=1e-4),
    )
    m = open_map(out)  # the lead's reader: rows, columns and shared edges check out
    rgb, _valid = m.read(0, 0, m.width, m.height)
    assert (m.width, m.height) == (2 * 1280, 2 * 1230)
    r0, c0 = g["top_px"] - top, g["left_px"] - left
    assert np.array_equal(rgb, world[r0 : r0 + m.height, c0 : c0 + m.width])  # pixel-exact, logo strip gone
    assert not np.all(rgb == MAGENTA, axis=-1).any()
    assert m.resolution_m == pytest.approx(res_at(RENDER_ZOOM) * math.cos(math.radians(47.02)), rel=2e-3)
    text = (out / "manifest.json").read_text() + "".join(rows)
    assert SECRET not in text and not partial_files(out)
    # resume: nothing to fetch
    n = server.requests
    report, _ = download_map(out, GOOGLE_BBOX, GOOGLE_ZOOM, provider, key=SECRET, policy=fast_policy(), progress=False)
    assert report.skipped == 4 and server.requests == n


def test_google_without_key_is_refused(monkeypatch):
    monkeypatch.delenv("AEROLOC_GOOGLE_KEY", raising=False)
    with pytest.raises(AerolocError, match="AEROLOC_GOOGLE_KEY"):
        read_key(GoogleStaticProvider())


def test_remove_partial_files_only_touches_temp_files(tmp_path):
    (tmp_path / "15" / "1").mkdir(parents=True)
    keep = tmp_path / "15" / "1" / "2.png"
    keep.write_bytes(b"x")
    (tmp_path / "15" / "1" / ".3.png.abc.part").write_bytes(b"x")
    assert remove_partial_files(tmp_path) == 1 and keep.exists() and len(list(tmp_path.rglob("*"))) == 3


def test_report_summary_lists_missing_tiles():
    r = DownloadReport(
        expected=3, downloaded=1, skipped=0, failed={"15/1/2": "HTTP 404", "15/1/3": "timeout"}, seconds=2.0
    )
    s = r.summary()
    assert "2 missing of 3" in s and "15/1/2" in s and "HTTP 404 (1)" in s and not r.complete
