"""Re-ranking: score each retrieved candidate by geometrically verified inliers, best K out.

The straightforward loop (dense matcher on every candidate x rotation) costs ~150 ms a pair, so the default is
two-stage: a cheap mutual-nearest-neighbour count on the stored descriptors ranks every (candidate, query
rotation) pair, the matcher + homography verification then runs on the ``max_verify`` most promising pairs in
that order, and stops early once a candidate is clearly verified. Candidates that were not verified keep their
prefilter order behind the verified ones. Ties keep the retrieval order (stable sort).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from aeroloc.errors import AerolocError
from aeroloc.localfeatures import extract, to_original

# Pipeline-level settings per re-ranker; ``features`` names the extractor+matcher in aeroloc.models.local.
DEFAULTS = {
    "query_side": 512,  # working resolution (longer side) of the query and of tiles, see localfeatures
    "tile_side": 512,
    "rotations": [0, 1, 2, 3],  # query rotations tried, in multiples of 90° CCW
    "prefilter": "mnn",  # "mnn" or "none" (verify every pair)
    "max_verify": 4,  # pairs verified by the matcher after the prefilter
    "early_exit": 120,  # stop verifying once a candidate reaches this many inliers
    "min_inliers": 35,  # below this the query is "not localized"
    "ransac_px": 4.0,  # MAGSAC threshold in working-resolution pixels
    "mnn_min_sim": 0.0,
}
RERANKERS = {
    "xfeat-lighterglue": {"features": "xfeat-lighterglue"},
    "xfeat-mnn": {"features": "xfeat-mnn", "prefilter": "none", "min_inliers": 25},
    "aliked-lightglue": {"features": "aliked-lightglue"},
    "disk-lightglue": {"features": "disk-lightglue"},
    "sift": {"features": "sift", "prefilter": "none", "min_inliers": 20},
    "superpoint-lightglue": {"features": "superpoint-lightglue"},
    "superpoint-superglue": {"features": "superpoint-superglue"},
    "selavpr": {"features": "selavpr", "prefilter": "none", "rotations": [0]},
}
DEFAULT_RERANKER = "xfeat-lighterglue"


def rerank_conf(name: str, overrides: dict | None = None) -> dict:
    if name not in RERANKERS:
        raise AerolocError(f"unknown re-ranker '{name}'; choose one of: {', '.join(sorted(RERANKERS))}")
    conf = {**DEFAULTS, **RERANKERS[name], **(overrides or {})}
    bad = set(overrides or {}) - set(conf)
    if bad:
        raise AerolocError(f"unknown re-ranker option(s) {sorted(bad)}")
    return conf


@dataclass
class Candidate:
    tile_id: str
    retrieval_rank: int
    prefilter: float = 0.0
    inliers: int = 0
    rot_k: int = 0
    H: np.ndarray | None = None  # query original px -> tile original px
    verified: bool = False
    n_matches: int = 0
    matches: tuple | None = None  # (query kpts, tile kpts, inlier mask) in original frames, for visualisation


@dataclass
class Reranked:
    candidates: list[Candidate]
    times_ms: dict = field(default_factory=dict)  # local_features, rerank


def mnn_count(d0: np.ndarray, d1: np.ndarray, min_sim: float = 0.0) -> int:
    """Number of mutual nearest neighbours between two descriptor sets (cosine)."""
    if len(d0) == 0 or len(d1) == 0:
        return 0
    a = d0 / (np.linalg.norm(d0, axis=1, keepdims=True) + 1e-8)
    b = d1 / (np.linalg.norm(d1, axis=1, keepdims=True) + 1e-8)
    sim = a @ b.T
    nn01, nn10 = sim.argmax(1), sim.argmax(0)
    mutual = nn10[nn01] == np.arange(len(a))
    return int(np.sum(mutual & (sim[np.arange(len(a)), nn01] > min_sim)))


class Reranker:
    """Holds the extractor/matcher and the tile feature store of one database."""

    def __init__(self, db, name: str, device="cpu", conf: dict | None = None):
        from aeroloc.localfeatures import store_for
        from aeroloc.models.local import build_reranker

        self.db, self.name = db, name
        self.conf = rerank_conf(name, conf)
        self.extractor, self.matcher = build_reranker(self.conf["features"], device)
        self.store = store_for(db, name, self.conf)
        self._have = self.store.names()

    def query_features(self, image: np.ndarray) -> list[dict]:
        return [extract(self.extractor, image, self.conf["query_side"], k) for k in self.conf["rotations"]]

    def tile_features(self, tile_ids: list[str]) -> dict[str, dict]:
        """From the store; tiles not there yet are extracted once and written (lazy cache)."""
        from aeroloc.images import read_image

        missing = [t for t in tile_ids if t not in self._have]
        if missing:
            new = {t: extract(self.extractor, read_image(self.db.folder / self.db.by_id[t].path),
                              self.conf["tile_side"]) for t in missing}
            self.store.write_many(new)
            self._have |= set(missing)
        with self.store.reader() as r:
            return {t: r.get(t) for t in tile_ids}

    def verify(self, qf: dict, tf: dict):
        from aeroloc.verify import verify_homography

        matches, _ = self.matcher.match(qf, tf)
        if len(matches) < 4:
            return 0, None, len(matches), None
        k0, k1 = to_original(qf), to_original(tf)
        thr = self.conf["ransac_px"] / float(tf["scale"])
        v = verify_homography(k0, k1, matches, threshold_px=thr)
        m0, m1 = k0[matches[:, 0]], k1[matches[:, 1]]
        return int(v.n_inliers), v.H, len(matches), (m0, m1, np.asarray(v.inliers, bool))

    def __call__(self, image: np.ndarray, tile_ids: list[str], top_k: int = 1) -> Reranked:
        t0 = time.perf_counter()
        qfs = self.query_features(image)
        tfs = self.tile_features(tile_ids)
        t1 = time.perf_counter()
        cands = [Candidate(t, i) for i, t in enumerate(tile_ids)]
        pairs = []  # (score, retrieval rank, rotation index)
        for c in cands:
            for ri, qf in enumerate(qfs):
                s = mnn_count(qf["descriptors"], tfs[c.tile_id]["descriptors"], self.conf["mnn_min_sim"]) \
                    if self.conf["prefilter"] == "mnn" else 0
                pairs.append((s, c.retrieval_rank, ri))
                c.prefilter = max(c.prefilter, s)
        if self.conf["prefilter"] == "mnn":
            pairs.sort(key=lambda p: (-p[0], p[1], p[2]))
            pairs = pairs[: self.conf["max_verify"]]
        for _, rank, ri in pairs:
            c = cands[rank]
            n_in, H, n_m, vis = self.verify(qfs[ri], tfs[c.tile_id])
            if n_in > c.inliers or not c.verified:
                if n_in >= c.inliers:
                    c.inliers, c.H, c.n_matches, c.matches = n_in, H, n_m, vis
                    c.rot_k = int(qfs[ri]["rot_k"])
            c.verified = True
            if c.inliers >= self.conf["early_exit"]:
                break
        order = sorted(cands, key=lambda c: (not c.verified, -c.inliers, -c.prefilter, c.retrieval_rank))
        t2 = time.perf_counter()
        return Reranked(order[: max(top_k, 1)] if top_k else order,
                        {"local_features": (t1 - t0) * 1000, "rerank": (t2 - t1) * 1000})
