"""Score a results CSV (name,lat,lon,top_tiles) against ground truth and a tile database."""

from __future__ import annotations

import json
from pathlib import Path

from aeroloc.core.errors import AerolocError


def add_arguments(p):
    p.add_argument("results", help="results CSV: name,lat,lon (empty = not localized),top_tiles (';'-separated)")
    p.add_argument("--truth", required=True, help="queries with ground truth (queries.csv, queries.txt, folder)")
    p.add_argument("--tiles", help="tile database folder (holds tiles.csv) for VPR recall")
    p.add_argument("--thresholds", default="10,25,50,100", help="metres, comma-separated (default %(default)s)")
    p.add_argument("--json", dest="json_out", help="write the metrics (and per-query rows) to this JSON file")


def parse_thresholds(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise AerolocError(f"--thresholds {text!r}: expected metres separated by commas, e.g. 10,25,50") from None
    if not vals or any(v <= 0 for v in vals):
        raise AerolocError(f"--thresholds {text!r}: thresholds must be positive")
    return vals


def run(args) -> int:
    from aeroloc.bench.metrics import evaluate, format_table
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.results import read_localizations
    from aeroloc.maps.tiling import load_tiles

    results = read_localizations(args.results)
    queries = load_queries(args.truth, require_images=False)
    tiles = load_tiles(args.tiles) if args.tiles else None
    metrics = evaluate(results, queries, tiles, parse_thresholds(args.thresholds))
    print(format_table(metrics))
    if args.json_out:
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(metrics, indent=1, default=str))
    return 0
