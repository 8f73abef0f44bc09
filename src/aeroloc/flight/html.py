"""The flight's offline HTML page: the estimated track over the map imagery (Leaflet inlined, the map as a Web
Mercator overlay: aeroloc.maps.webmap), each frame a dot coloured by what placed it (global fix, tracked,
coasted), the truth track and a red error line per frame when truth is given, and a popup per frame (time,
source, status, sigma, error). Everything is inlined: the page works without network."""

from __future__ import annotations

import html
import json
import math

from aeroloc.core.io import atomic_write_text
from aeroloc.flight.outputs import truth_error

COLOURS = {"global fix": "#1f78b4", "tracked": "#33a02c", "coasted": "#ff7f00"}

PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>{title}</title>
<style>{css}
body{{margin:0;font:14px sans-serif}} #map{{height:80vh}} #summary{{padding:8px 12px}}
.legend span{{display:inline-block;width:12px;height:12px;border-radius:6px;margin:0 4px 0 12px}}</style>
</head><body><div id="map"></div><div id="summary" {data}>{summary}<div class="legend">{legend}</div></div>
<script>{js}</script><script>
const D = {payload};
const map = L.map('map', {{preferCanvas: false, attributionControl: false}});
let bounds = null;
if (D.overlay) {{
  L.imageOverlay(D.overlay.url, D.overlay.bounds, {{opacity: 0.95}}).addTo(map);
  L.polygon(D.overlay.outline, {{color: '#555', weight: 1, fill: false}}).addTo(map);
  bounds = L.latLngBounds(D.overlay.bounds);
}}
if (D.truth.length) L.polyline(D.truth, {{color: '#ffffff', weight: 2, dashArray: '4 4'}}).addTo(map);
const track = L.polyline(D.points.map(p => [p.lat, p.lon]), {{color: '#e31a1c', weight: 2}}).addTo(map);
let n = 0;
for (const p of D.points) {{
  if (p.truth) L.polyline([[p.lat, p.lon], p.truth], {{color: '#d7301f', weight: 1}}).addTo(map);
  L.circleMarker([p.lat, p.lon], {{radius: 4, color: D.colours[p.source] || '#888', weight: 1, fillOpacity: 0.9}})
    .bindPopup(p.popup).addTo(map);
  n++;
}}
map.fitBounds(D.points.length ? track.getBounds().pad(0.2) : bounds);
document.getElementById('summary').dataset.drawn = String(n);
</script></body></html>"""


def _points(points, truth: dict | None) -> list[dict]:
    out = []
    for p in points:
        if not p.localized:
            continue
        t = (truth or {}).get(p.name)
        err = truth_error(p, t) if t else math.nan
        popup = (
            f"<b>{html.escape(p.name)}</b><br>t = {p.time:.2f} s<br>{html.escape(p.source)}: "
            f"{html.escape(p.status)}<br>sigma {p.sigma_m:.1f} m" + (f"<br>error {err:.1f} m" if t else "")
        )
        out.append(
            {"lat": p.lat, "lon": p.lon, "source": p.source, "popup": popup, "truth": [t[0], t[1]] if t else None}
        )
    return out


def write_track_html(path, points, map_path, truth: dict | None = None, title: str = "aeroloc track") -> None:
    """The page for ``points`` (TrackPoint) over the map at ``map_path``; ``truth`` name -> (lat, lon)."""
    from aeroloc.core.errors import AerolocError
    from aeroloc.maps.webmap import leaflet_assets, map_overlay

    js, css = leaflet_assets()
    try:
        overlay = map_overlay(map_path, max_px=1400)
    except AerolocError:
        overlay = None  # the map file is not readable here: the track alone
    pts = _points(points, truth)
    truth_line = [[truth[p.name][0], truth[p.name][1]] for p in points if truth and p.name in truth]
    by = {s: sum(p.source == s for p in points) for s in ("global fix", "tracked", "coasted", "lost")}
    errs = [truth_error(p, truth[p.name]) for p in points if p.localized and truth and p.name in truth]
    summary = f"{len(points)} frames: " + ", ".join(f"{n} {s}" for s, n in by.items())
    if errs:
        summary += f"; median error {sorted(errs)[len(errs) // 2]:.1f} m, max {max(errs):.1f} m"
    legend = "".join(f"<span style='background:{c}'></span>{s}" for s, c in COLOURS.items())
    data = f'data-points="{len(pts)}" data-truth="{int(bool(truth_line))}"'
    payload = json.dumps({"overlay": overlay, "points": pts, "truth": truth_line, "colours": COLOURS})
    page = PAGE.format(
        title=html.escape(title),
        css=css,
        js=js,
        payload=payload.replace("</", "<\\/"),
        summary=html.escape(summary),
        legend=legend,
        data=data,
    )
    atomic_write_text(path, page)
