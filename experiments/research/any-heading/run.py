"""Run the any-heading localizer (anyloc.py) on one query set and prior mode; write results + metrics CSV.

usage: run.py SET MODE [--limit N] [--tag TAG] [key=value ...]
SET: levir-north levir-any szada-north szada-any naip-dev naip-rot ; MODE: none rough exact
"""
import csv, json, math, os, sys, time
import numpy as np
import cv2
from pyproj import Geod

sys.path.insert(0, os.path.dirname(__file__))
import anyloc as al

D = str(__import__("pathlib").Path(__file__).resolve().parents[4] / "shared" / "data")
SETS = {
    "levir-north": (f"{D}/multi-region/levir-tx/map.tif", f"{D}/multi-region/levir-tx/north"),
    "levir-any": (f"{D}/multi-region/levir-tx/map.tif", f"{D}/multi-region/levir-tx/any"),
    "szada-north": (f"{D}/multi-region/szada-hu/map.tif", f"{D}/multi-region/szada-hu/north"),
    "szada-any": (f"{D}/multi-region/szada-hu/map.tif", f"{D}/multi-region/szada-hu/any"),
    "naip-dev": (f"{D}/naip-nd/map_20200831.tif", f"{D}/naip-nd/dev"),
    "naip-rot": (f"{D}/naip-nd/map_20200831.tif", f"{D}/naip-nd/dev-rotated"),
}
PARAMS = {"coarse_budget": 2_500_000, "coarse_max": 1_000_000, "coarse_min": 60_000, "s_range": [0.25, 1.05], "a_step": 15.0, "s_step": 1.26, "T": 32, "K": 4, "K_ref": 3, "T_ref": [64], "T_final": 128, "rounds": 2}
FACTORS = [2 ** (k / 3) for k in range(0, 16)]
_PYR = {}


def pyramid(map_path):
    if map_path not in _PYR:
        m = al.GeoMap(map_path)
        t = time.perf_counter()
        _PYR[map_path] = (m, al.build_pyramid(m, FACTORS))
        print(f"pyramid {time.perf_counter() - t:.1f} s", file=sys.stderr)
    return _PYR[map_path]


def priors(row, mode, rng, map_gsd, gsd_mult=1.0):
    h = float(row["heading_deg"]) if row.get("heading_deg") else None
    g = float(row["gsd_m"]) if row.get("gsd_m") else map_gsd  # naip: queries at the map's 5 m
    g *= gsd_mult  # null test on another region's map: same footprint in map px as on its own map
    if mode == "none":
        return al.Priors()
    if mode == "exact":
        return al.Priors(heading=h, heading_tol=0.0, gsd=g, gsd_ratio=1.0)
    # rough: gsd x U[0.8, 1.25] (log-uniform), heading +- U[-15, 15]
    return al.Priors(heading=(h + rng.uniform(-15, 15)) % 360, heading_tol=15.0,
                     gsd=g * math.exp(rng.uniform(math.log(0.8), math.log(1.25))), gsd_ratio=1.25)


def run(set_name, mode, params, limit=None, tag="", map_override=None, gsd_mult=1.0):
    map_path, qdir = SETS[set_name]
    if map_override:
        map_path = map_override
    m, levels = pyramid(map_path)
    rows = list(csv.DictReader(open(f"{qdir}/queries.csv")))[:limit]
    rng = np.random.default_rng(12345)
    geod = Geod(ellps="WGS84")
    out = []
    for r in rows:
        img = cv2.cvtColor(cv2.imread(f"{qdir}/queries/{r['name']}"), cv2.COLOR_BGR2RGB)
        pri = priors(r, mode, rng, m.gsd, gsd_mult)
        t, c = time.perf_counter(), time.process_time()
        res = al.localize(levels, m, img, pri, params)
        dt, cpu = time.perf_counter() - t, time.process_time() - c
        err = geod.inv(float(r["lon"]), float(r["lat"]), res["lon"], res["lat"])[2] if res["ok"] else float("inf")
        th = float(r["heading_deg"]) if r.get("heading_deg") else float("nan")
        gs = float(r["gsd_m"]) * gsd_mult / m.gsd if r.get("gsd_m") else 1.0
        out.append({"name": r["name"], "err_m": err, "s": dt, "cpu_s": cpu, **{k: res.get(k) for k in
                    ("lat", "lon", "angle", "scale", "score", "second", "ratio", "coarse", "n_hyp")},
                    "true_heading": th, "true_scale": gs})
    return m, out


def summarize(m, out, accept=None):
    t = max(5.0, 2 * m.gsd); wrong_r = max(25.0, 10 * m.gsd)
    acc = [accept(o) if accept else True for o in out]
    e = np.array([o["err_m"] if a else np.inf for o, a in zip(out, acc)])
    return {"n": len(out), "georef@t": float(np.mean(e <= t)), "t_m": t, "not_loc": int(np.isinf(e).sum()),
            "wrong": int(((e > wrong_r) & np.isfinite(e)).sum()), "s_med": float(np.median([o["s"] for o in out])), "cpu_med": float(np.median([o["cpu_s"] for o in out])),
            "raw_within_t": float(np.mean([o["err_m"] <= t for o in out]))}


if __name__ == "__main__":
    set_name, mode = sys.argv[1], sys.argv[2]
    params = dict(PARAMS); limit = None; tag = ""
    for a in sys.argv[3:]:
        k, v = a.split("=")
        if k == "limit": limit = int(v)
        elif k == "tag": tag = v
        else: params[k] = json.loads(v)
    m, out = run(set_name, mode, params, limit)
    fn = f"results/{set_name}-{mode}{tag}.csv"
    os.makedirs(os.path.dirname(fn), exist_ok=True)
    with open(fn, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(out[0])); w.writeheader(); w.writerows(out)
    for o in out:
        print(f"{o['name']:28s} err {o['err_m']:8.1f} s {o['s']:.2f} ang {o['angle'] or 0:6.1f} (true {o['true_heading']:6.1f}) "
              f"sc {o['scale'] or 0:.3f} (true {o['true_scale']:.3f}) score {o['score'] or 0:.3f} ratio {o['ratio'] or 0:.2f} coarse {o['coarse'] or 0:.3f}")
    print(json.dumps(summarize(m, out)))
