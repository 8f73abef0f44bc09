"""Experiment (issue 13): every tile also described at K turns (read from a larger map window, turned, cut back to
the tile), the upright query searched over all (tile, turn) entries. Prints retrieval recall upright vs turned
database and how well the best turn tells the heading. usage: python turned_views.py SET [K=8] [WORK]
(SET as in benchmarks/localize_speed.py: levir-any, szada-any, naip-rotated, levir-north, ...)"""

import sys, csv, time, numpy as np, cv2
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "benchmarks"))
from localize_speed import SETS

from aeroloc import build_database, read_image, load_queries
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.retriever import Retriever
from aeroloc.retrieval.descriptors import describe_image
from aeroloc.bench.metrics import tile_contains
from aeroloc.maps.sources import open_map

name = sys.argv[1]
K = int(sys.argv[2]) if len(sys.argv) > 2 else 8
mp, qp, tm = SETS[name]
WORK = Path(sys.argv[3] if len(sys.argv) > 3 else "/tmp/aeroloc-turned-db")
db = build_database(mp, WORK / f"{mp.parent.name}-{tm}", tile_m=tm)
ret = Retriever(db)
m = open_map(str(mp))
cache = WORK / f"turned_{mp.parent.name}_{K}.npy"
if cache.exists():
    D = np.load(cache)
else:
    t0 = time.time()
    D = []
    for t in db.tiles:
        side = int(np.ceil(np.hypot(t.width, t.height))) + 2
        cx, cy = t.col + t.width / 2, t.row + t.height / 2
        c0, r0 = int(cx - side / 2), int(cy - side / 2)
        c1, r1 = max(c0, 0), max(r0, 0)
        c2, r2 = min(c0 + side, m.width), min(r0 + side, m.height)
        big = np.zeros((side, side, 3), np.uint8)
        rgb, _ = m.read(c1, r1, c2 - c1, r2 - r1)
        big[r1 - r0 : r2 - r0, c1 - c0 : c2 - c0] = rgb
        row = []
        for i in range(K):
            ang = -360.0 * i / K  # clockwise turn of the tile (cv2 positive = CCW)
            M = cv2.getRotationMatrix2D((cx - c0, cy - r0), ang, 1.0)
            M[0, 2] -= t.col - c0
            M[1, 2] -= t.row - r0
            v = cv2.warpAffine(big, M, (t.width, t.height), flags=cv2.INTER_LINEAR)
            row.append(describe_image(ret.model, v, "cpu")[0][0])
        D.append(row)
    D = np.asarray(D, np.float32)
    np.save(cache, D)
    print(f"described {len(db.tiles)}x{K} in {time.time() - t0:.0f}s")
N = len(db.tiles)
flat = D.reshape(N * K, -1)
heads = {r["name"]: float(r["heading_deg"]) for r in csv.DictReader(open(qp))}
qs = load_queries(qp, priors="none")


def rank_of(order, true):
    for i, j in enumerate(order):
        if j in true:
            return i
    return 99


res, ranks_true = [], []
for q in qs:
    im = ret.shrink(read_image(q.path))
    d = describe_image(ret.model, im, "cpu")[0][0]
    true = {j for j, t in enumerate(db.tiles) if tile_contains(t, q.lat, q.lon)}
    s_up = D[:, 0] @ d
    up_rank = rank_of(np.argsort(-s_up), true)
    s = flat @ d
    best = s.reshape(N, K).max(1)
    rot_rank = rank_of(np.argsort(-best), true)
    e = int(np.argmax(s))
    turn = 360.0 * (e % K) / K
    # best turn on the true tile
    tt = max(true, key=lambda j: (D[j] @ d).max()) if true else None  # the true tile nearest the photo
    tturn = 360.0 * int(np.argmax(D[tt] @ d)) / K if tt is not None else None
    h = heads[q.name]
    if tt is not None:
        ranks_true.append(list(np.argsort(-(D[tt] @ d))).index(int(round(h / (360 / K))) % K))
    err = lambda a: abs((a - h + 180) % 360 - 180)
    res.append((q.name, h, up_rank, rot_rank, turn, err(turn), tturn, err(tturn) if tturn is not None else None))
    print(
        f"{q.name[:22]:22} h={h:6.1f} up_rank={up_rank:2d} rot_rank={rot_rank:2d} top1turn={turn:5.1f} err={err(turn):5.1f} trueTileTurn={tturn} err={err(tturn):5.1f}"
    )
import statistics

for n in (1, 3, 5, 20):
    print(
        f"recall@{n}: upright {np.mean([r[2] < n for r in res]):.3f}  turned-db {np.mean([r[3] < n for r in res]):.3f}"
    )
print("top1 turn within 22.5:", np.mean([r[5] <= 22.5 for r in res]), " within 30:", np.mean([r[5] <= 30 for r in res]))
print("true tile's best turn within 22.5:", np.mean([r[7] <= 22.5 for r in res]))
# rank of the correct 45-degree bin among the K turns, by the true tile's similarities
print("rank of the right turn on the true tile:", np.bincount(ranks_true, minlength=K), "mean", np.mean(ranks_true))
