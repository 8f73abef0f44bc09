#!/usr/bin/env python
"""Ground that a map shows twice: where no localizer can tell two places apart, so "two places match" is the
right answer there and a fix at the other copy is the other copy's coordinate, not a confusion of two places.

Each map is cut into patches (``--patch-px`` map pixels square, half-overlapping, at most 96 px after shrinking); each patch
is correlated (normalised cross-correlation) with the whole map, and its *echo* is the best peak farther than
max(25 m, 10 map px) + one patch from itself. Patches whose echo exceeds ``--echo`` are doubled ground; the
echoes of a real doubling share one offset (two overlapping scenes of one mosaic), scattered offsets are texture.
Prints per map the echo distribution and the offsets of the doubled patches, and per query set the queries whose
true centre lies on doubled ground (what the data says, not what aeroloc answered: its results are printed beside
when a results CSV is given, ``--results SET=CSV``).

usage: python benchmarks/repeated_ground.py [--patch-px 128] [--echo 0.6] [--shared 8] [--results szada-north=out.csv ...]
"""

from __future__ import annotations

import argparse
import csv
import math
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MR = DATA / "multi-region"
MAPS = {
    "naip-nd": (DATA / "naip-nd/map_20200831.tif", ["naip-nd/dev", "naip-nd/dev-rotated"]),
    "toledo": (DATA / "toledo/orthomosaic.tif", ["toledo"]),
    "levir-tx": (MR / "levir-tx/map.tif", ["multi-region/levir-tx/north", "multi-region/levir-tx/any"]),
    "szada-hu": (MR / "szada-hu/map.tif", ["multi-region/szada-hu/north", "multi-region/szada-hu/any"]),
}


def gray_and_valid(path: Path, shrink: int) -> tuple[np.ndarray, np.ndarray]:
    """The map in grey (float32) and its valid mask (alpha or nodata), shrunk by ``shrink`` with area averaging."""
    import cv2
    import rasterio

    with rasterio.open(path) as ds:
        rgb = ds.read([1, 2, 3]).astype(np.float32).mean(0)
        valid = ds.dataset_mask() > 0
    if shrink > 1:
        size = (rgb.shape[1] // shrink, rgb.shape[0] // shrink)
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        valid = cv2.resize(valid.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999
    return rgb, valid


def echoes(path: Path, patch_px: int) -> dict:
    """Every textured, fully valid patch's echo: {(col, row) centre in map px: (score, (dx, dy) map px)}."""
    import cv2
    import rasterio

    with rasterio.open(path) as ds:
        gsd = abs(ds.transform.a) if ds.crs and ds.crs.is_projected else None
    if gsd is None:
        raise SystemExit(f"{path}: needs a projected CRS (metres)")
    side = patch_px
    shrink = max(1, math.ceil(side / 96))
    img, valid = gray_and_valid(path, shrink)
    p = int(round(side / shrink))
    fill = float(img[valid].mean())
    img = np.where(valid, img, fill).astype(np.float32)
    exclude = (max(25.0, 10 * gsd) / gsd / shrink) + p  # shrunk px around the patch itself
    out = {}
    for y in range(0, img.shape[0] - p + 1, p // 2):
        for x in range(0, img.shape[1] - p + 1, p // 2):
            if not valid[y : y + p, x : x + p].all():
                continue
            t = img[y : y + p, x : x + p]
            if t.std() < 4.0:  # no texture: water, haze
                continue
            res = cv2.matchTemplate(img, t, cv2.TM_CCOEFF_NORMED)
            yy, xx = np.ogrid[: res.shape[0], : res.shape[1]]
            res[(yy - y) ** 2 + (xx - x) ** 2 <= exclude**2] = -1.0
            k = int(res.argmax())
            ey, ex = divmod(k, res.shape[1])
            centre = ((x + p / 2) * shrink, (y + p / 2) * shrink)
            out[centre] = (float(res.flat[k]), ((ex - x) * shrink, (ey - y) * shrink), p * shrink / 2)
    return {"gsd": gsd, "patches": out}


def doubled_patches(patches: dict, echo: float, shared: int, tol_px: float = 16.0) -> dict:
    """The patches whose echo is at least ``echo`` and whose offset at least ``shared`` such patches repeat (within
    ``tol_px``, either sign: the two copies echo each other): a doubled stretch of ground, not a lone look-alike."""
    strong = {c: v for c, v in patches.items() if v[0] >= echo}
    offs = np.array([v[1] for v in strong.values()], float).reshape(-1, 2)
    keep = {}
    for c, v in strong.items():
        o = np.asarray(v[1], float)
        near = (np.hypot(*(offs - o).T) <= tol_px).sum() + (np.hypot(*(offs + o).T) <= tol_px).sum()
        if near >= shared:
            keep[c] = v
    return keep


def doubled_queries(folder: Path, m, patches: dict) -> list[tuple[str, float, tuple]]:
    """The queries of ``folder`` whose true centre lies inside a doubled patch: (name, echo, offset)."""
    with open(folder / "queries.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    found = []
    for r in rows:
        col, row = m.latlon_to_pixel(float(r["lat"]), float(r["lon"]))
        best = None
        for (cx, cy), (score, off, half) in patches.items():
            if abs(col - cx) <= half and abs(row - cy) <= half:
                best = max(best or (score, off), (score, off))
        if best is not None:
            found.append((r["name"], best[0], best[1]))
    return found


def main() -> None:
    from aeroloc.maps.sources import open_map

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--patch-px", type=int, default=128, help="patch side in map pixels (NCC needs texture enough)")
    ap.add_argument("--echo", type=float, default=0.7, help="echo score above which a patch may be doubled ground")
    ap.add_argument("--shared", type=int, default=8, help="... when at least this many such patches share its offset")
    ap.add_argument("--maps", default=",".join(MAPS))
    ap.add_argument(
        "--results", nargs="*", default=[], help="SET=results.csv (aeroloc localize output) to print beside"
    )
    a = ap.parse_args()
    results = {}
    for spec in a.results:
        name, path = spec.split("=", 1)
        with open(path, newline="") as f:
            results[name] = {r["name"]: r for r in csv.DictReader(f)}
    for name in a.maps.split(","):
        path, sets = MAPS[name]
        e = echoes(path, a.patch_px)
        scores = sorted(s for s, _, _ in e["patches"].values())
        q = np.quantile(scores, [0.5, 0.9, 0.99, 1.0]) if scores else [math.nan] * 4
        doubled = doubled_patches(e["patches"], a.echo, a.shared, tol_px=16.0)
        print(
            f"\n## {name}: {len(scores)} patches of {a.patch_px * e['gsd']:.0f} m; echo median {q[0]:.2f}, p90 {q[1]:.2f}, "
            f"p99 {q[2]:.2f}, max {q[3]:.2f}; doubled (echo >= {a.echo}, >= {a.shared} sharing an offset): "
            f"{len(doubled)}"
        )
        offsets = Counter((round(o[0] / 16) * 16, round(o[1] / 16) * 16) for _, o, _ in doubled.values())
        for (dx, dy), n in offsets.most_common(6):
            print(f"  offset ({dx:+.0f}, {dy:+.0f}) map px = {math.hypot(dx, dy) * e['gsd']:.0f} m: {n} patches")
        m = open_map(path)
        for s in sets:
            folder = DATA / s
            found = doubled_queries(folder, m, doubled)
            with open(folder / "queries.csv", newline="") as f:
                total = sum(1 for _ in csv.DictReader(f))
            print(f"  {s}: {len(found)} of {total} queries on doubled ground")
            key = s.split("/")[-2] + "-" + s.split("/")[-1] if "/" in s else s
            for qn, score, off in found:
                got = results.get(key, {}).get(qn)
                extra = f" | aeroloc: {got['status'][:60]}" if got else ""
                print(f"    {qn}: echo {score:.2f} at {math.hypot(*off) * e['gsd']:.0f} m{extra}")


if __name__ == "__main__":
    main()
