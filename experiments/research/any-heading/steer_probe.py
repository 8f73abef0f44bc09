"""Research probe (2026-12-04): can XFeat's descriptors be *steered* under quarter turns, so that one extraction
stands in for four (the cascade extracts a photo of unknown heading at up to 8 turns)?

A steerer (Bökman et al., "Steerers", CVPR 2024) is a linear map S_k with desc(rot90^k(image)) ~ S_k desc(image)
at the same ground point. XFeat was not trained for one, so S_k is fitted here, per map, on its own tiles (no
truth involved): the dense 64-d descriptor map of a tile turned by k quarter turns against the tile's map turned
the same way (cell for cell, exact correspondences), orthogonal Procrustes.

  A. north-up photos turned by k quarter turns: screen inliers (the cascade's screen) on their true tile with
     features extracted at the undoing turn vs the upright extraction steered by S_{4-k};
  B. photos at any heading: the 8 turns (0 and 45° extracted, the others steered) screened on the 3 upright-
     retrieved tiles; is the best turn the one nearest the true heading (truth for scoring only)?

usage: python steer_probe.py DB NORTH_QUERIES.csv ANY_QUERIES.csv [--n 12]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import torch

from aeroloc.bench.metrics import first_hit
from aeroloc.core.frames import resize_to_side
from aeroloc.core.images import read_image
from aeroloc.localization.cascade import Reranker
from aeroloc.matching.features import extract, turn_gap
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.retriever import Retriever


def dense_map(extractor, image: np.ndarray, side: int = 512) -> np.ndarray:
    """XFeat's L2-normalised 64 x H/8 x W/8 descriptor map of ``image`` at the cascade's working side."""
    im = resize_to_side(image, side)[0]
    h, w = im.shape[:2]
    im = np.ascontiguousarray(im[: h // 32 * 32, : w // 32 * 32])
    x = torch.tensor(im).permute(2, 0, 1)[None].float() / 255
    with torch.inference_mode():
        x, _, _ = extractor.model.preprocess_tensor(x)
        m, _, _ = extractor.model.net(x)
    return torch.nn.functional.normalize(m, dim=1)[0].numpy()


def fit_steerers(db, extractor, n_tiles: int = 30, seed: int = 0) -> dict[int, np.ndarray]:
    """S_k (64 x 64, orthogonal) for k = 1-3 quarter turns counter-clockwise, fitted on ``n_tiles`` map tiles."""
    rng = np.random.default_rng(seed)
    tiles = [db.tiles[i] for i in rng.choice(len(db.tiles), min(n_tiles, len(db.tiles)), replace=False)]
    images = [db.tile_image(t.id) for t in tiles]
    upright = [dense_map(extractor, im) for im in images]
    steerers = {0: np.eye(64, dtype=np.float32)}
    for k in (1, 2, 3):
        a, b = [], []
        for im, m0 in zip(images, upright):
            mk = dense_map(extractor, np.ascontiguousarray(np.rot90(im, k)))
            r = np.rot90(m0, k, axes=(1, 2))
            if r.shape == mk.shape:
                a.append(r.reshape(64, -1).T)
                b.append(mk.reshape(64, -1).T)
        a, b = np.concatenate(a), np.concatenate(b)
        u, _, vt = np.linalg.svd(b.T @ a)
        steerers[k] = (u @ vt).astype(np.float32)
        p = a @ steerers[k].T
        print(f"S_{k}: {len(a)} cells, cosine to the turned extraction {np.mean(np.sum(a * b, 1)):.3f} unsteered, "
              f"{np.mean(np.sum(p * b, 1) / np.linalg.norm(p, axis=1)):.3f} steered")
    return steerers


def steered(f: dict, s: np.ndarray) -> dict:
    """``f`` with its descriptors steered: the same ground points (``to_original`` unchanged), other turn."""
    d = f["descriptors"].astype(np.float32) @ s.T
    return {**f, "descriptors": d / np.linalg.norm(d, axis=1, keepdims=True)}


def rows_of(path: Path, n: int):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))[:n]
    return [(r, read_image(path.parent / "queries" / r["name"])) for r in rows]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("db")
    ap.add_argument("north", type=Path)
    ap.add_argument("any", type=Path)
    ap.add_argument("--n", type=int, default=12)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    db = Database(args.db)
    rr = Reranker(db, "xfeat-lighterglue", "cpu", {"screen_threads": 1})
    ret = Retriever(db, None, "cpu", 1)
    steerers = fit_steerers(db, rr.extractor)

    print("\nA. photo turned k quarter turns: screen inliers on its true tile, extracted / steered")
    for r, img in rows_of(args.north, args.n):
        top = ret(img, 20, rotations=4).tile_ids
        hit = first_hit(tuple(top), db.by_id, float(r["lat"]), float(r["lon"]))
        if hit is None:
            continue
        tile = rr.tile_features([top[hit]])[top[hit]]
        cells = []
        for k in (1, 2, 3):
            photo = np.ascontiguousarray(np.rot90(img, k))
            undo = 4 - k
            true = rr.screen_pair(extract(rr.extractor, photo, 512, undo), tile)[0]
            steer = rr.screen_pair(steered(extract(rr.extractor, photo, 512, 0), steerers[undo]), tile)[0]
            cells.append(f"{true}/{steer}")
        print(f"  {r['name']:26s} k=1,2,3: {'  '.join(cells)}")

    print("\nB. heading probe: best of 8 turns (0 and 45° extracted, the rest steered) on the top-3 tiles")
    right = near = n = 0
    for r, img in rows_of(args.any, args.n):
        top = ret(img, 3).tile_ids
        tfs = rr.tile_features(top)
        truth = min(range(8), key=lambda k: turn_gap(float(r["heading_deg"]), k))
        score = {}
        for base in (0, 4):
            f = extract(rr.extractor, img, 512, base)
            for q in range(4):
                g = steered(f, steerers[q]) if q else f
                score[base + q] = max(rr.screen_pair(g, tfs[t])[0] for t in top)
        order = sorted(score, key=score.get, reverse=True)
        n += 1
        right += order[0] == truth
        near += order.index(truth) <= 1
        print(f"  {r['name']:26s} true turn {truth}, best {order[0]}, scores {[score[k] for k in range(8)]}")
    print(f"best turn = true turn {right}/{n}; true turn among the best two {near}/{n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
