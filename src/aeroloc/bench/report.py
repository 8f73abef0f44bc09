"""One self-contained HTML page per benchmark run: tables, plots, a Leaflet map of ground truth vs estimates
per query over the map imagery, and match visualisations that enlarge on click.

Offline by construction: Leaflet's JS/CSS come from the ``xstatic-leaflet`` package in site-packages and are
inlined (their icon images as data URIs); plots, the map imagery and match images are base64 data URIs. The
map imagery is downscaled (WebP with alpha) and reprojected to Web Mercator (Leaflet's display CRS), so it sits exactly under
the points whatever the map's own CRS; when the map file is not readable here, the tile footprints or the
points alone are shown. The page layout, CSS and JS live in ``report_template.html`` beside this file.
"""

from __future__ import annotations

import html
import json
import math
from datetime import datetime
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.maps.webmap import (  # noqa: F401 (the generic web-map pieces; map_overlay re-exported for callers)
    jpeg_data_uri,
    leaflet_assets,
    map_overlay,
    png_data_uri,
    rgba_data_uri,
)

TEMPLATE = Path(__file__).with_name("report_template.html")
ERROR_COLOURS = ["#1a9850", "#91cf60", "#fee08b", "#fc8d59", "#d73027"]  # <= t1 … <= t4, beyond
NOT_LOCALIZED_COLOUR = "#6b6b6b"
MAX_MATCH_IMAGES = 12
MAX_TILE_FOOTPRINTS = 5000


def match_image_uris(path) -> tuple[str, str] | None:
    """(thumbnail, enlarged) data URIs of a match visualisation file, None if unreadable."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"))
    except (OSError, UnidentifiedImageError):
        return None
    return jpeg_data_uri(rgb, 420, 78), jpeg_data_uri(rgb, 1400, 85)


def tile_footprints(db_folder) -> list[list[list[float]]] | None:
    from aeroloc.maps.tiling import load_tiles

    try:
        tiles = load_tiles(db_folder)
    except (AerolocError, OSError):
        return None
    if len(tiles) > MAX_TILE_FOOTPRINTS:
        return None
    out = []
    for t in tiles:
        lat, lon = t.pixel_to_latlon([0, t.width, t.width, 0], [0, 0, t.height, t.height])
        out.append([[round(float(a), 7), round(float(b), 7)] for a, b in zip(lat, lon)])
    return out


# --- page ---------------------------------------------------------------------------------------------------
def _num(v):
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v


def default_config(rows: list[dict], thresholds) -> dict:
    """The configuration shown first on the map: best Georeference Recall at the tightest threshold, then the
    lowest median error; re-ranked configurations first."""
    t = f"georef_recall@{min(thresholds):g}m" if thresholds else None

    def score(r):
        return (r.get("reranker") is not None, r.get(t) or 0.0, -(_num(r.get("median_error_m")) or 1e18))

    return max(rows, key=score)


def sample_matches(qrows: list[dict], k: int = MAX_MATCH_IMAGES) -> list[dict]:
    """Up to ``k`` queries with a match image: the worst and the best half each, so failures are visible."""
    with_img = [q for q in qrows if q.get("match_image") and Path(q["match_image"]).is_file()]
    key = lambda q: (_num(q.get("error_m")) is None, _num(q.get("error_m")) or 0.0)  # noqa: E731
    with_img.sort(key=key)
    if len(with_img) <= k:
        return with_img
    worst = with_img[len(with_img) - k // 2 :]
    best = with_img[: k - len(worst)]
    return best + worst


def _label(r: dict, fields) -> str:
    from aeroloc.bench.tables import describe

    return describe(r, fields)


def dataset_view(idx: int, dataset: str, rows: list[dict], qrows_by_key: dict, thresholds) -> tuple[dict, str]:
    """The map data (JSON for the page's script) and the match gallery HTML of one query set."""
    from aeroloc.bench.tables import varying

    fields = varying(rows, always=("method", "reranker"))
    shown = default_config(rows, thresholds)
    gallery, images = _gallery(idx, qrows_by_key.get(shown["config_key"], []))
    configs = [
        {
            "label": _label(r, fields),
            "key": r["config_key"],
            "shown": r is shown,
            "points": _points(qrows_by_key.get(r["config_key"], []), images if r is shown else {}),
        }
        for r in rows
    ]
    view = {
        "id": f"map{idx}",
        "dataset": dataset,
        "thresholds": list(thresholds),
        "configs": configs,
        "overlay": None,
        "tiles": None,
        "colours": ERROR_COLOURS,
        "grey": NOT_LOCALIZED_COLOUR,
    }
    _add_map_layers(view, shown)
    gallery_html = ""
    if gallery:
        gallery_html = (
            f"<h3>Match visualisations — {html.escape(_label(shown, fields))}</h3>"
            f"<p class=hint>Query (left) against the chosen tile (right); inlier matches green. "
            f"Click to enlarge.</p><div class=gallery>{''.join(gallery)}</div>"
        )
    return view, gallery_html


def _gallery(idx: int, qrows: list[dict]) -> tuple[list[str], dict]:
    """The thumbnails (HTML figures) of the sampled match images, and query name -> image element id."""
    gallery, images = [], {}
    for q in sample_matches(qrows):
        uris = match_image_uris(q["match_image"])
        if uris is None:
            continue
        img_id = f"m{idx}-{len(images)}"
        images[q["name"]] = img_id
        err = _num(q.get("error_m"))
        cap = f"{q['name']} — {'not localized' if err is None else f'{err:.1f} m'}, {q.get('inliers') or 0} inliers"
        gallery.append(
            f"<figure class=thumb><img id={img_id} src='{uris[0]}' data-full='{uris[1]}' "
            f"alt='{html.escape(q['name'])}' loading=lazy><figcaption>{html.escape(cap)}</figcaption></figure>"
        )
    return gallery, images


def _points(qrows: list[dict], images: dict) -> list[dict]:
    """One configuration's queries for the map: truth, estimate (None when not localized), error and details;
    ``img`` names the gallery image of the query, if any."""
    pts = []
    for q in qrows:
        est = (
            [q["est_lat"], q["est_lon"]]
            if _num(q.get("est_lat")) is not None and _num(q.get("est_lon")) is not None
            else None
        )
        pts.append(
            {
                "n": q["name"],
                "t": [q["true_lat"], q["true_lon"]],
                "e": est,
                "err": _num(q.get("error_m")),
                "st": q.get("status") or "",
                "inl": q.get("inliers"),
                "rank": q.get("vpr_rank"),
                "img": images.get(q["name"]),
            }
        )
    return pts


def _add_map_layers(view: dict, shown: dict) -> None:
    """The map imagery under the points (or why it is missing) and the tile footprints of the shown config."""
    try:
        view["overlay"] = map_overlay(shown["map_path"])
    except Exception as exc:
        view["overlay_error"] = str(exc) or type(exc).__name__
    if shown.get("db"):
        tiles = tile_footprints(shown["db"])
        if tiles:
            view["tiles"] = {"label": f"tiles (zoom {shown['zoom']:g}, overlap {shown['overlap']:g})", "polys": tiles}


def _finite(obj):
    """JSON-safe copy: NaN/inf -> None (the page treats None as 'not localized' / 'not measured')."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def _runs_html(runs: list[dict]) -> str:
    e = html.escape
    rows = "".join(
        f"<tr><td class=lab>{e(r['run_id'])}</td><td class=lab>{e(str(r.get('hostname')))}</td>"
        f"<td class=num>{r.get('cpu_count')}</td><td class=lab>{e(str(r.get('torch_version')))}</td>"
        f"<td class=lab>{e(str(r.get('device')))}</td><td class=lab>{e(str(r.get('started_at')))}</td>"
        f"<td class=lab>{e(str(r.get('finished_at') or '–'))}</td><td class=lab>{e(str(r.get('status')))}</td>"
        f"<td class=lab>{e(str(r.get('code') or '–'))}</td></tr>"
        for r in runs
    )
    return (
        "<table class=runs><thead><tr><th>run</th><th>host</th><th>CPUs</th><th>torch</th><th>device</th>"
        f"<th>started (UTC)</th><th>finished</th><th>status</th>"
        '<th title="hash of the aeroloc source that measured the run (aeroloc.core.provenance)">code</th>'
        f"</tr></thead><tbody>{rows}</tbody></table>"
    )


def write_report(
    path,
    title: str,
    rows: list[dict],
    qrows_by_key: dict[str, list[dict]],
    tables,
    plots,
    runs: list[dict],
    thresholds=(),
    description: str = "",
    files: dict | None = None,
) -> Path:
    """Write the page to ``path``. ``rows``: result rows (``ResultStore.results``) of the configurations to
    show; ``qrows_by_key``: config key -> per-query rows; ``tables``/``plots`` from tables.py/plots.py;
    ``files``: label -> path of side files (CSV, Markdown, LaTeX) linked relatively."""
    from aeroloc.bench.tables import by_dataset

    if not rows:
        raise AerolocError(f"{path}: no results to report")
    e = html.escape
    js, css = leaflet_assets()  # first: without Leaflet there is no page to build
    sections, views, toc = [], [], []
    for i, (dataset, rs) in enumerate(by_dataset(rows).items()):
        view, gallery = dataset_view(i, dataset, rs, qrows_by_key, thresholds)
        views.append(view)
        toc.append(f"<a href='#ds{i}'>{e(dataset)}</a>")
        sections.append(_section(i, dataset, rs, view, gallery, tables, plots))
    links = " · ".join(f"<a href='{e(str(p))}'>{e(k)}</a>" for k, p in (files or {}).items())
    subs = {
        "__TITLE__": e(title),
        "__DESCRIPTION__": e(description),
        "__GENERATED__": e(f"{datetime.now():%Y-%m-%d %H:%M} · {len(rows)} configurations"),
        "__TOC__": " · ".join(toc),
        "__FILES__": links,
        "__RUNS__": _runs_html(runs),
        "__SECTIONS__": "\n".join(sections),
    }
    return _write_page(Path(path), _fill_template(subs, views, js, css))


def _section(i: int, dataset: str, rs: list[dict], view: dict, gallery: str, tables, plots) -> str:
    """The HTML section of one query set: the map, its gallery, its tables and plots."""
    e = html.escape
    ts = "".join(t.html() for t in tables if getattr(t, "dataset", dataset) == dataset)
    ps = "".join(
        f"<figure class=plot><img src='{png_data_uri(p.path)}' data-full='' alt='{e(p.title)}'>"
        f"<figcaption>{e(p.title)}</figcaption></figure>"
        for p in plots
        if p.dataset == dataset
    )
    n_q = max((r.get("n_queries") or 0) for r in rs)
    note = (
        f"<p class=warn>map imagery unavailable: {e(view.get('overlay_error', ''))}</p>"
        if view.get("overlay_error")
        else ""
    )
    return (
        f"<section id=ds{i}><h2>{e(dataset)}</h2>"
        f"<p class=sub>map <code>{e(rs[0]['map'])}</code> · {n_q} queries · {len(rs)} configurations</p>"
        f"<h3>Ground truth vs estimate</h3><p class=hint>White dots: ground truth; coloured dots: estimates, "
        f"joined by a line, coloured by error; grey rings: not localized. Click a point for details.</p>{note}"
        f"<label class=picker>configuration <select id=map{i}-pick></select></label>"
        f"<div class=map id=map{i}></div>"
        f"{gallery}<h3>Tables</h3>{ts}<h3>Plots</h3><div class=plots>{ps}</div></section>"
    )


def _fill_template(subs: dict, views: list[dict], js: str, css: str) -> str:
    """The page: the template with the text placeholders replaced, then Leaflet and the map data inlined."""
    data = json.dumps(_finite(views), allow_nan=False, default=str).replace("</", "<\\/")
    page = TEMPLATE.read_text(encoding="utf-8")
    for k, v in subs.items():
        page = page.replace(k, v)
    # code last: it must not be searched for placeholders
    page = page.replace("/*__LEAFLET_CSS__*/", css).replace("/*__DATA__*/", data)
    return page.replace("/*__LEAFLET_JS__*/", js.replace("</script", "<\\/script"))


def _write_page(path: Path, page: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(path)
    return path
