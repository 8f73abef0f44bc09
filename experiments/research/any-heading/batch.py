"""Batch: every set x prior mode for one map in one process (the map pyramid is built once); writes res/*.csv.
usage: batch.py MAPKEY MODES LIMIT_NONE [null]"""
import csv, json, os, sys
sys.path.insert(0, os.path.dirname(__file__))
import run

GROUPS = {"levir": ["levir-north", "levir-any"], "szada": ["szada-north", "szada-any"], "naip": ["naip-rot", "naip-dev"]}
NULL = {"levir": ("szada-north", 0.5 / 1.5), "szada": ("levir-north", 1.5 / 0.5), "naip": ("szada-north", 5.0 / 1.5)}  # x = this map gsd / own map gsd


def save(name, out):
    os.makedirs("results", exist_ok=True)
    with open(f"results/{name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(out[0])); w.writeheader(); w.writerows(out)


if __name__ == "__main__":
    key, modes, lim_none = sys.argv[1], sys.argv[2].split(","), int(sys.argv[3])
    sets = GROUPS[key]
    mp = run.SETS[sets[0]][0]
    if "null" in sys.argv[4:]:  # another region's queries on this map: every answer is wrong
        qs, mult = NULL[key]
        for mode in modes:
            m, out = run.run(qs, mode, run.PARAMS, lim_none if mode == "none" else None, map_override=mp, gsd_mult=mult)
            for o in out: o["err_m"] = float("inf") if o["err_m"] != float("inf") else o["err_m"]
            save(f"null-{key}-{mode}", out); print("null", key, mode, flush=True)
        sys.exit()
    for mode in modes:
        for s in sets:
            m, out = run.run(s, mode, run.PARAMS, lim_none if mode == "none" else None)
            save(f"{s}-{mode}", out)
            print(s, mode, json.dumps(run.summarize(m, out)), flush=True)
