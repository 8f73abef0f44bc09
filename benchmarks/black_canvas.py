#!/usr/bin/env python
"""Photos on a black canvas: the same photos as they are, turned about their centre on a black-cornered canvas,
and centred on a black canvas 1.5x their side, each localized (``--priors``: the atlas's modes, none by default)
with the canvas cut away (the pipeline's default: the photo alone, turned back upright and cut,
aeroloc.core.canvas) and kept (``LocalizeOptions(trim_canvas=False)``).

Why: a photo that arrives padded or de-rotated carries a black border that the local-feature networks normalise
with the imagery (README #13, "A photo on a black canvas"). This prints what that costs, so a remedy can be
measured against it. The canvases keep the photo's centre at theirs, so the truth columns stay exact; they are
written as PNG (no JPEG fringe) under ``--work``. The truth is read for scoring only.

usage: python benchmarks/black_canvas.py DB QUERIES.csv [--n 20] [--match 2009,2010] [--work DIR]
                                        [--priors none|rough|exact]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ANGLES = (45, 100, 137, 225, 300, 160, 200, 250, 75, 20)  # degrees the content turns clockwise, cycled over
# the photos (aeroloc.core.frames.turned: a canvas that holds the whole photo, its centre at the photo's)


def on_padded_canvas(photo: np.ndarray) -> np.ndarray:
    """``photo`` centred on a black canvas 1.5x its side (the same margin each side)."""
    h, w = photo.shape[:2]
    y0, x0 = round(0.25 * h), round(0.25 * w)
    canvas = np.zeros((h + 2 * y0, w + 2 * x0, 3), np.uint8)
    canvas[y0 : y0 + h, x0 : x0 + w] = photo
    return canvas


def score(localizer, queries, images: dict, priors: dict, map_gsd: float) -> tuple[int, int, int, float]:
    """(placed, within t, wrong, median s per photo) of ``images`` (name -> RGB) against ``queries``' truth,
    t and wrong as the atlas counts them (aeroloc.bench.metrics.scaled_recall)."""
    from aeroloc.bench.metrics import scaled_recall
    from aeroloc.core import geo

    per_query, seconds = [], []
    for q in queries:
        t0 = time.perf_counter()
        res = localizer(q.name, images[q.name], priors=priors[q.name])
        seconds.append(time.perf_counter() - t0)
        err = float(geo.geodesic_distance(q.lat, q.lon, res.lat, res.lon)) if res.localized else float("nan")
        per_query.append({"error_m": err})
    r = scaled_recall(per_query, map_gsd)
    placed = sum(math.isfinite(q["error_m"]) for q in per_query)
    return placed, round(r["georef_recall@t"] * len(per_query)), r["wrong_n"], statistics.median(seconds)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("db")
    ap.add_argument("queries")
    ap.add_argument("--n", type=int, default=20, help="photos (every other one of those matching, in order)")
    ap.add_argument("--match", default="", help="comma-separated substrings a photo's name must hold (one)")
    ap.add_argument("--work", type=Path, default=None, help="where the canvases are written (default: a temp dir)")
    ap.add_argument("--priors", default="none", choices=("none", "rough", "exact"), help="as the atlas's modes")
    args = ap.parse_args(argv)

    from aeroloc import Database, LocalizeOptions, Localizer, load_queries, read_image
    from aeroloc.core.frames import turned

    keys = [k for k in args.match.split(",") if k]
    queries = [q for q in load_queries(args.queries, priors=args.priors) if not keys or any(k in q.name for k in keys)]
    queries = queries[::2][: args.n]
    db = Database(args.db)
    gsd = float(db.info["map"]["resolution_m"])
    t_m, wrong_m = max(5.0, 2 * gsd), max(25.0, 10 * gsd)  # as scaled_recall counts them: for the header
    work = args.work or Path(tempfile.mkdtemp(prefix="black-canvas-"))
    work.mkdir(parents=True, exist_ok=True)
    photos = {q.name: read_image(q.path) for q in queries}
    turns = {n: -ANGLES[i % len(ANGLES)] for i, n in enumerate(photos)}  # OpenCV's angle: counter-clockwise
    variants = {
        "as they are": photos,
        "turned on a black-cornered canvas": {n: turned(p, turns[n], "black")[0] for n, p in photos.items()},
        "centred on a black canvas 1.5x their side": {n: on_padded_canvas(p) for n, p in photos.items()},
    }
    given = {q.name: q.priors for q in queries}
    # a canvas's priors: its pixels are the photo's (same ground resolution), its heading the photo's plus the turn
    priors = {
        "as they are": given,
        "turned on a black-cornered canvas": {
            n: None if p is None else p.for_view(variants["turned on a black-cornered canvas"][n].shape[1], turns[n])
            for n, p in given.items()
        },
        "centred on a black canvas 1.5x their side": {
            n: None if p is None else p.for_view(variants["centred on a black canvas 1.5x their side"][n].shape[1])
            for n, p in given.items()
        },
    }
    for label, images in variants.items():  # written out, to look at
        folder = work / label.replace(" ", "-")
        folder.mkdir(exist_ok=True)
        for n, im in images.items():
            cv2.imwrite(str(folder / (Path(n).stem + ".png")), im[..., ::-1])
    trimmed, kept = Localizer(db, LocalizeOptions()), Localizer(db, LocalizeOptions(trim_canvas=False))
    print(
        f"{len(queries)} photos of {args.queries}, priors {args.priors}; t {t_m:.0f} m, wrong > {wrong_m:.0f} m; "
        f"canvases in {work}"
    )
    print("| the same photos | canvas | placed | within t | wrong | median s |\n|---|---|---|---|---|---|")
    for label, images in variants.items():
        # photos as they are sit on no canvas: the view (aeroloc.core.canvas) leaves them as they are
        runs = {"-": trimmed} if images is photos else {"the photo alone (as built)": trimmed, "kept": kept}
        for how, localizer in runs.items():
            placed, within, wrong, med = score(localizer, queries, images, priors[label], gsd)
            print(f"| {label} | {how} | {placed} | {within} | {wrong} | {med:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
