"""Fit the confidence and uncertainty models of aeroloc.localization.confidence on benchmark results, and print
the reliability table (confidence bins vs observed share within t), each map's fixes scored by a model fitted
without that map.

usage: python benchmarks/calibrate.py RUNS/results.sqlite [...]   (e.g. the output of experiments/atlas.yaml)
       python benchmarks/calibrate.py --shipped RUNS/results.sqlite [...]   (the tables of the models aeroloc ships)
"""

from __future__ import annotations

import itertools
import sqlite3
import sys
from collections import defaultdict

import numpy as np
from scipy.optimize import minimize

from aeroloc.localization.confidence import MODELS, SOURCES, StageModel, evidence, source_of
from aeroloc.maps.sources import open_map

BINS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 1.0001)


def load(paths: list[str]) -> list[dict]:
    """Localized fixes of the newest run of every configuration: map, set, stage, evidence (inliers or
    ratio), error, t."""
    rows, gsd = [], {}
    for p in paths:
        db = sqlite3.connect(p)
        db.row_factory = sqlite3.Row
        newest = db.execute(
            "SELECT config_key, map, map_path, queries, MAX(run_id) AS run_id FROM results GROUP BY config_key"
        ).fetchall()
        for r in newest:
            if r["map_path"] not in gsd:
                gsd[r["map_path"]] = open_map(r["map_path"]).resolution_m
            g = gsd[r["map_path"]]
            for q in db.execute(
                "SELECT status, inliers, error_m FROM query_results WHERE run_id=? AND config_key=?",
                (r["run_id"], r["config_key"]),
            ):
                if q["error_m"] is None or not str(q["status"]).startswith("localized"):
                    continue
                rows.append(
                    {
                        "map": r["map"],
                        "set": r["queries"],
                        "source": source_of(q["status"]),
                        "evidence": evidence(q["status"], int(q["inliers"] or 0)),
                        "error_m": float(q["error_m"]),
                        "gsd": g,
                        "t_m": max(5.0, 2.0 * g),
                    }
                )
    return rows


def fit(rows: list[dict]) -> dict[str, StageModel]:
    """Per stage: logistic regression of 'within t' on ln(evidence) (L2-regularised, so a stage whose every fix
    is right gets a high but finite confidence), and the sigma scale from the median error."""
    models = {}
    for s in SOURCES:
        rs = [r for r in rows if r["source"] == s]
        if not rs:
            models[s] = StageModel(a=0.0, b=0.0, sigma0_m=1.0, sigma_px=0.5)
            continue
        x = np.log(np.maximum(1, [r["evidence"] for r in rs]))
        y = np.array([r["error_m"] <= r["t_m"] for r in rs], float)

        def loss(w, x=x, y=y):
            z = w[0] + w[1] * x
            return float(np.sum(np.logaddexp(0, z) - y * z) + 0.5 * (w[0] ** 2 + w[1] ** 2) / 25.0)

        # more inliers never mean less confidence: the slope is bounded at 0 (few misses can't fix its sign)
        a, b = minimize(loss, np.zeros(2), method="L-BFGS-B", bounds=[(None, None), (0.0, None)]).x
        # sigma0 + sigma_px * gsd fitted to error / 1.1774 by least absolute deviation (a median fit): the median
        # radial error of a 2-D normal is 1.1774 sigma
        e = np.array([r["error_m"] for r in rs]) / 1.1774
        g = np.array([r["gsd"] for r in rs])
        s0, s1 = minimize(
            lambda w, e=e, g=g: float(np.abs(e - w[0] - w[1] * g).sum()),
            [1.0, 0.5],
            method="Powell",
            bounds=[(0.0, None), (0.0, None)],
        ).x
        models[s] = StageModel(round(float(a), 3), round(float(b), 3), round(float(s0), 3), round(float(s1), 3))
    return models


def scored_by(r: dict, models: dict[str, StageModel]) -> dict:
    """Fix ``r`` with the confidence and sigma its stage's model gives it."""
    mod = models[r["source"]]
    return {**r, "conf": mod.confidence(r["evidence"]), "sigma": mod.sigma_m(r["evidence"], r["gsd"])}


def reliability(rows: list[dict]) -> list[dict]:
    """Leave-one-map-out: each map's fixes scored by the model fitted on the other maps."""
    scored = []
    for m in sorted({r["map"] for r in rows}):
        models = fit([r for r in rows if r["map"] != m])
        scored += [scored_by(r, models) for r in rows if r["map"] == m]
    return scored


def shipped(rows: list[dict]) -> list[dict]:
    """Every fix scored by the models aeroloc ships (aeroloc.localization.confidence.MODELS): how calibrated the
    confidence users get is on these results."""
    return [scored_by(r, MODELS) for r in rows]


def print_tables(scored: list[dict]) -> None:
    print("| confidence bin | fixes | mean confidence | observed within t |")
    print("|---|---|---|---|")
    for lo, hi in itertools.pairwise(BINS):
        b = [r for r in scored if lo <= r["conf"] < hi]
        if b:
            hit = np.mean([r["error_m"] <= r["t_m"] for r in b])
            print(f"| {lo:.2f}-{min(hi, 1):.2f} | {len(b)} | {np.mean([r['conf'] for r in b]):.3f} | {hit:.3f} |")
    print()
    print("| set | fixes | within sigma | within 2 sigma | median sigma (m) | median error (m) |")
    print("|---|---|---|---|---|---|")
    by = defaultdict(list)
    for r in scored:
        by[r["set"]].append(r)
    for s, rs in sorted(by.items()):
        e, sg = np.array([r["error_m"] for r in rs]), np.array([r["sigma"] for r in rs])
        print(
            f"| {s} | {len(rs)} | {np.mean(e <= sg):.2f} | {np.mean(e <= 2 * sg):.2f} | {np.median(sg):.2f} | {np.median(e):.2f} |"
        )


def main(argv: list[str]) -> int:
    ship = "--shipped" in argv
    rows = load([a for a in argv if a != "--shipped"])
    print(f"{len(rows)} fixes; stages: { {s: sum(r['source'] == s for r in rows) for s in SOURCES} }\n")
    if ship:
        print_tables(shipped(rows))
        return 0
    print_tables(reliability(rows))
    print("\nMODELS fitted on every map (paste into aeroloc/localization/confidence.py):")
    for s, m in fit(rows).items():
        print(f'    "{s}": {m!r},')
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
