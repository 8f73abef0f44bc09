"""Score main's localize CSVs (also partial *.part files): Georef@t, not localized, wrong, median total_ms."""
import csv, glob, sys
import numpy as np
from pyproj import Geod

D = str(__import__("pathlib").Path(__file__).resolve().parents[4] / "shared" / "data" / "multi-region")
TRUTH = {"levir-north": (f"{D}/levir-tx/north/queries.csv", 0.5), "levir-any": (f"{D}/levir-tx/any/queries.csv", 0.5),
         "szada-north": (f"{D}/szada-hu/north/queries.csv", 1.5), "szada-any": (f"{D}/szada-hu/any/queries.csv", 1.5)}
geod = Geod(ellps="WGS84")
for key, (tq, g) in TRUTH.items():
    for fn in glob.glob(f"base-{key}*.csv*"):
        if fn.endswith((".config", ".time", ".log")):
            continue
        truth = {r["name"]: r for r in csv.DictReader(open(tq))}
        rows = list(csv.DictReader(open(fn)))
        t, wr = max(5, 2 * g), max(25, 10 * g)
        e = []
        for r in rows:
            q = truth[r["name"]]
            e.append(geod.inv(float(q["lon"]), float(q["lat"]), float(r["lon"]), float(r["lat"]))[2] if r["lat"] else np.inf)
        e = np.array(e)
        ms = [float(r["total_ms"]) for r in rows if r.get("total_ms")]
        print(f"| {key} | {fn.split('/')[-1]} | {len(rows)} | {np.mean(e <= t):.3f} | {int(np.isinf(e).sum())} | "
              f"{int(((e > wr) & np.isfinite(e)).sum())} | {np.median(ms) / 1000:.1f} (wall, load ~20) |")
