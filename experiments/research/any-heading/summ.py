"""Tables from res/*.csv under an acceptance rule: accept iff ratio >= R and score >= S.
usage: summ.py [R] [S]   (prints markdown: per set x mode Georef@t, not localized, wrong, median CPU s/query)"""
import csv, glob, math, os, sys
import numpy as np

GSD = {"levir": 0.5, "szada": 1.5, "naip": 5.0}


def load(fn):
    return [{k: (float(v) if k != "name" and v not in ("", "None") else v) for k, v in r.items()} for r in csv.DictReader(open(fn))]


def table(R, S):
    lines = ["| set | mode | n | Georef@t | t (m) | not loc. | wrong | raw within t | CPU s/q median | wall s/q median |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for fn in sorted(glob.glob("results/*.csv")):
        b = os.path.basename(fn)[:-4]
        if b.startswith("null"):
            continue
        rows = load(fn)
        g = GSD[b.split("-")[0]]
        t, wr = max(5.0, 2 * g), max(25.0, 10 * g)
        acc = [isinstance(o["ratio"], float) and o["ratio"] >= R and o["score"] >= S for o in rows]
        e = np.array([o["err_m"] if a else np.inf for o, a in zip(rows, acc)])
        raw = np.array([o["err_m"] for o in rows])
        set_, mode = b.rsplit("-", 1)
        lines.append(f"| {set_} | {mode} | {len(rows)} | {np.mean(e <= t):.3f} | {t:g} | {int(np.isinf(e).sum())} | "
                     f"{int(((e > wr) & np.isfinite(e)).sum())} | {np.mean(raw <= t):.3f} | "
                     f"{np.median([o['cpu_s'] for o in rows]):.2f} | {np.median([o['s'] for o in rows]):.2f} |")
    return "\n".join(lines)


def separation():
    """ratio/score of right (err <= t) vs wrong raw answers and of the null tests (another region's map)."""
    right, wrong, null = [], [], []
    for fn in glob.glob("results/*.csv"):
        b = os.path.basename(fn)
        for o in load(fn):
            if not isinstance(o.get("ratio"), float):
                continue
            g = GSD[b.split("-")[1 if b.startswith("null") else 0]]
            pt = (o["ratio"], o["score"], b)
            if b.startswith("null"):
                null.append(pt)
            elif o["err_m"] <= max(5.0, 2 * g) * 2:
                right.append(pt)
            elif o["err_m"] > max(25.0, 10 * g):
                wrong.append(pt)
    for name, L in (("right", right), ("wrong", wrong), ("null", null)):
        if L:
            r = np.array([p[0] for p in L]); s = np.array([p[1] for p in L])
            print(f"{name}: n={len(L)} ratio min/p5/p50/max {r.min():.2f}/{np.percentile(r,5):.2f}/{np.median(r):.2f}/{r.max():.2f}"
                  f" score min/p50/max {s.min():.3f}/{np.median(s):.3f}/{s.max():.3f}")
    top = sorted(wrong + null, key=lambda p: -p[0])[:5]
    print("highest non-right ratios:", [(round(p[0], 2), round(p[1], 3), p[2]) for p in top])


def rule_search():
    """Acceptance (ratio >= R, score >= S) pairs that accept no wrong answer and no null answer, most rights."""
    pts = []
    for fn in glob.glob("results/*.csv"):
        b = os.path.basename(fn)
        for o in load(fn):
            if not isinstance(o.get("ratio"), float):
                continue
            g = GSD[b.split("-")[1 if b.startswith("null") else 0]]
            bad = b.startswith("null") or o["err_m"] > max(25.0, 10 * g)
            pts.append((o["ratio"], o["score"], bad, not bad and o["err_m"] <= max(5.0, 2 * g)))
    best = []
    for R in np.arange(1.0, 2.01, 0.05):
        for S in np.arange(0.0, 0.41, 0.02):
            acc = [p for p in pts if p[0] >= R and p[1] >= S]
            nbad = sum(p[2] for p in acc)
            best.append((nbad, -sum(p[3] for p in acc), round(R, 2), round(S, 2)))
    best.sort()
    print("rules (bad accepted, -rights accepted, R, S):", best[:8])


if __name__ == "__main__":
    R = float(sys.argv[1]) if len(sys.argv) > 1 else 0.0
    S = float(sys.argv[2]) if len(sys.argv) > 2 else -1.0
    separation(); rule_search()
    print(table(R, S))
