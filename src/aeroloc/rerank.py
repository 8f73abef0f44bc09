"""Re-ranking: score each retrieved candidate by geometrically verified inliers, best K out.

The straightforward loop (a learned matcher on every candidate x query rotation) costs ~150 ms+ a pair, so
re-ranking runs in two stages on features that are extracted once per query and stored per tile:

1. **screen**: mutual nearest neighbours on the stored descriptors + homography verification (MAGSAC) gives
   every visited candidate a verified inlier count in a few ms. Query rotations (multiples of 90°, for photos
   taken at any heading) are all tried on the first ``rotation_probe`` candidates and until one rotation
   reaches ``min_screen`` inliers; that rotation is then used for the rest. Candidates are visited in retrieval order and the screen stops early once one
   reaches ``early_exit`` inliers (the rest keep their retrieval order behind it).
2. **verify**: the re-ranker's own matcher (e.g. LighterGlue) re-matches the ``max_verify`` best screened
   candidates; its verified inliers decide their final order and give the homography used for alignment.

Ordering: matcher-verified candidates by inliers, then screened ones by screen inliers, then the unvisited
in retrieval order; ties keep the retrieval order (stable).
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
    "rotation_probe": 3,  # candidates on which every rotation is tried
    "screen": True,  # stage 1 (MNN + MAGSAC on all visited candidates); False = matcher on every pair
    "screen_min_sim": 0.7,  # cosine threshold of the screen's mutual nearest neighbours
    "early_exit": 40,  # screen inliers that end the screen (wrong tiles reached <= 16 on NAIP)
    "max_verify": 1,  # candidates re-matched by the re-ranker's matcher (0 = screen only)
    "min_inliers": 35,  # below this (the matcher's inliers, or the screen's if it ran alone): "not localized"
    "min_screen": 20,  # the best candidate's screen inliers must reach this too (an independent check)
    "ransac_px": 4.0,  # MAGSAC threshold in working-resolution pixels
    "extractor": {},  # overrides of the extractor conf (e.g. max_keypoints), see models.local.registry
    "matcher": {},  # overrides of the matcher conf
}
RERANKERS = {
    "xfeat-lighterglue": {"features": "xfeat-lighterglue"},
    "xfeat-mnn": {"features": "xfeat-mnn", "max_verify": 0, "min_inliers": 25},
    "aliked-lightglue": {"features": "aliked-lightglue"},
    "disk-lightglue": {"features": "disk-lightglue"},
    "sift": {"features": "sift", "screen": False, "rotations": [0], "min_inliers": 20},
    "superpoint-lightglue": {"features": "superpoint-lightglue"},
    "superpoint-superglue": {"features": "superpoint-superglue"},
    "selavpr": {"features": "selavpr", "screen": False, "rotations": [0]},
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


def similarity_fit(p0: np.ndarray, p1: np.ndarray, threshold_px: float):
    """(3x3 matrix or None, inlier mask) of a RANSAC similarity transform p0 -> p1."""
    import cv2

    A, inl = cv2.estimateAffinePartial2D(p0.astype(np.float32), p1.astype(np.float32), method=cv2.RANSAC,
                                         ransacReprojThreshold=threshold_px, maxIters=2000, confidence=0.999)
    if A is None:
        return None, np.zeros(len(p0), bool)
    return np.vstack([A, [0.0, 0.0, 1.0]]), inl.ravel().astype(bool)


def feature_overrides(conf: dict) -> dict:
    return {"extractor": conf["extractor"], "matcher": conf["matcher"]}


@dataclass
class Candidate:
    tile_id: str
    retrieval_rank: int
    screen: int = -1  # screen inliers (-1 = not visited)
    inliers: int = -1  # matcher inliers (-1 = not verified by the matcher)
    rot_k: int = 0
    H: np.ndarray | None = None  # query original px -> tile original px
    n_matches: int = 0
    matches: tuple | None = None  # (query kpts, tile kpts, inlier mask) in original frames, for visualisation

    @property
    def score(self) -> int:
        """The matcher's verified inliers when it ran, else the screen's."""
        return self.inliers if self.inliers >= 0 else max(self.screen, 0)

    def take(self, n_inliers, H, n_matches, vis, rot_k, stage: str) -> None:
        better = self.H is None or n_inliers > (self.screen if stage == "screen" else self.inliers)
        if stage == "screen":
            self.screen = max(self.screen, n_inliers)
        else:
            self.inliers = max(self.inliers, n_inliers)
        if better:
            self.H, self.n_matches, self.matches, self.rot_k = H, n_matches, vis, rot_k


@dataclass
class Reranked:
    candidates: list[Candidate]
    times_ms: dict = field(default_factory=dict)  # local_features, rerank
    n_screened: int = 0
    n_verified: int = 0


def mutual_nn(d0: np.ndarray, d1: np.ndarray, min_sim: float = 0.0) -> np.ndarray:
    """(M, 2) index pairs of mutual nearest neighbours (cosine similarity above ``min_sim``)."""
    if len(d0) == 0 or len(d1) == 0:
        return np.zeros((0, 2), np.int64)
    a = d0 / (np.linalg.norm(d0, axis=1, keepdims=True) + 1e-8)
    b = d1 / (np.linalg.norm(d1, axis=1, keepdims=True) + 1e-8)
    sim = a @ b.T
    nn01, nn10 = sim.argmax(1), sim.argmax(0)
    idx = np.arange(len(a))
    keep = (nn10[nn01] == idx) & (sim[idx, nn01] > min_sim)
    return np.stack([idx[keep], nn01[keep]], 1).astype(np.int64)


class Reranker:
    """Holds the extractor/matcher and the tile feature store of one database."""

    def __init__(self, db, name: str, device="cpu", conf: dict | None = None):
        from aeroloc.localfeatures import store_for
        from aeroloc.models.local import build_reranker

        self.db, self.name = db, name
        self.conf = rerank_conf(name, conf)
        self.extractor, self.matcher = build_reranker(self.conf["features"], device, feature_overrides(self.conf))
        self.store = store_for(db, name, self.conf)
        self._have = self.store.names()

    def query_features(self, image: np.ndarray) -> dict[int, dict]:
        return {k % 4: extract(self.extractor, image, self.conf["query_side"], k) for k in self.conf["rotations"]}

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

    def _verify(self, qf: dict, tf: dict, matches: np.ndarray):
        from aeroloc.verify import homography_is_sane, verify_homography

        if len(matches) < 4:
            return 0, None, len(matches), None
        k0, k1 = to_original(qf), to_original(tf)
        thr = self.conf["ransac_px"] / float(tf["scale"])
        v = verify_homography(k0, k1, matches, threshold_px=thr)
        H, inliers = v.H, np.asarray(v.inliers, bool)
        if H is not None and not homography_is_sane(H, tuple(int(x) for x in qf["orig_size"]))[0]:
            # nadir imagery: a full homography fitted on clustered inliers can extrapolate wildly; refit the
            # better-conditioned similarity model (rotation, scale, shift) and count its own inliers
            H, inliers = similarity_fit(k0[matches[:, 0]], k1[matches[:, 1]], thr)
        vis = (k0[matches[:, 0]], k1[matches[:, 1]], inliers)
        return int(inliers.sum()), H, len(matches), vis

    def screen_pair(self, qf, tf):
        return self._verify(qf, tf, mutual_nn(qf["descriptors"], tf["descriptors"], self.conf["screen_min_sim"]))

    def match_pair(self, qf, tf):
        matches, _ = self.matcher.match(qf, tf)
        return self._verify(qf, tf, np.asarray(matches, np.int64).reshape(-1, 2))

    def __call__(self, image: np.ndarray, tile_ids: list[str], top_k: int = 1) -> Reranked:
        t0 = time.perf_counter()
        qfs = self.query_features(image)
        tfs = self.tile_features(tile_ids)
        t1 = time.perf_counter()
        cands = [Candidate(t, i) for i, t in enumerate(tile_ids)]
        rots = list(qfs)
        n_screened = n_verified = 0
        if self.conf["screen"]:
            best_rot, best_rot_score = rots[0], -1
            for c in cands:
                # every rotation on the first candidates, and until one rotation is clearly supported
                probe = c.retrieval_rank < self.conf["rotation_probe"] or best_rot_score < self.conf["min_screen"]
                for k in (rots if probe else [best_rot]):
                    c.take(*self.screen_pair(qfs[k], tfs[c.tile_id]), k, "screen")
                    n_screened += 1
                    if probe and c.screen > best_rot_score and c.rot_k == k:
                        best_rot, best_rot_score = k, c.screen
                if c.screen >= self.conf["early_exit"]:
                    break
            to_verify = sorted((c for c in cands if c.screen >= 0), key=lambda c: (-c.screen, c.retrieval_rank))
            to_verify = [(c, [c.rot_k]) for c in to_verify[: self.conf["max_verify"]]]
        else:  # the straightforward loop: the matcher on every candidate x rotation
            to_verify = [(c, rots) for c in cands]
        for c, ks in to_verify:
            for k in ks:
                c.take(*self.match_pair(qfs[k], tfs[c.tile_id]), k, "verify")
                n_verified += 1
        order = sorted(cands, key=lambda c: (c.inliers < 0, -c.inliers, c.screen < 0, -c.screen, c.retrieval_rank))
        t2 = time.perf_counter()
        return Reranked(order[: top_k] if top_k else order,
                        {"local_features": (t1 - t0) * 1000, "rerank": (t2 - t1) * 1000}, n_screened, n_verified)
