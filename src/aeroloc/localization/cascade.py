"""Re-ranking: score each retrieved candidate by geometrically verified inliers, best K out.

The straightforward loop (a learned matcher on every candidate x query rotation) costs ~150 ms+ a pair, so
re-ranking runs in two stages on features that are extracted once per query and stored per tile:

1. **screen**: mutual nearest neighbours on the stored descriptors + a RANSAC similarity (the nadir model,
   2-point samples; ``screen_geometry``) gives every visited candidate a verified inlier count in ~9 ms (a MAGSAC
   homography, as before 2026-12-05: ~14 ms, most of it 10,000 iterations on wrong pairs). Query rotations
   (multiples of 90°, for photos taken at any heading) are tried lazily: the first ``rotation_probe`` candidates
   at the upright rotation, the next rotation only while none reached ``min_screen`` inliers, later candidates at
   the heading found;
   each rotation's features are extracted on first use, so an upright photo costs one
   extraction; a database with turned tiles (``aeroloc build --local-turns``) screens the upright photo against
   each tile turned back instead (:meth:`Reranker._pair`), so its screens cost one extraction whatever the
   heading (levir-tx/any, no prior: ~8 extractions, ~0.3 s, a query before); the matcher still gets the query
   turned. With the heading unknown the diagonals (a quarter turn + 45°) are tried too, since the matchers
   bridge only ~20-40° of rotation: on the probe always, on later candidates where the dominant orientations of
   query and tile (aeroloc.matching.orientation) say the query lies nearer a diagonal. Candidates are visited in retrieval order and the screen stops early once one reaches
   ``early_exit`` inliers (the rest keep their retrieval order behind it).
2. **verify**: when no candidate's screen reached ``accept_screen`` inliers, the re-ranker's own matcher (e.g.
   LighterGlue, ~0.3-1 s a pair on CPU) re-matches the best screened candidates, at most ``max_verify``, until
   one reaches ``min_inliers``; its verified inliers decide their order and give the transform for alignment.
   Candidates screened below ``weak_screen_min`` are not matched: in 96 matcher runs on screens of 8-11 (every
   shared set, 485 queries) LighterGlue found at most 12 inliers, against the 30 a pass needs.
   The default fits a similarity to the matcher's matches (``geometry``): on 1059 NAIP + Toledo pairs wrong
   tiles reached <= 24 similarity inliers and right ones a median of 89 (NAIP) / 356 (Toledo), and wrong tiles
   reached <= 20 screen inliers, so a strong screen is trusted as it is and the matcher settles the rest.
   A best match that stays weak is re-matched on the map window it points at (``refine_min``, aeroloc.localization.window).
   A candidate the matcher fails although its screen settled a heading is matched once more with the query turned
   by the screen transform's own angle (``screen_turns``): the screen's mutual nearest neighbours hold at 25° of
   residual turn where the learned matcher breaks, and the screen's transform tells the turn that is left.

Ordering: matcher-verified candidates by inliers, then screened ones by screen inliers, then the unvisited
in retrieval order; ties keep the retrieval order (stable).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field

import numpy as np

from aeroloc.core.frames import inverse_turn
from aeroloc.localization.agreement import screen_agreed
from aeroloc.matching.features import DIAGONAL, extract, to_original, turn_gap, turned_name
from aeroloc.matching.registry import build_reranker, feature_overrides, rerank_conf


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
    query: dict = field(default_factory=dict)  # rot_k -> the query's features extracted on the way
    ranked: list[Candidate] = field(default_factory=list)  # every candidate, best first (``candidates``: top K)
    features: QueryFeatures | None = None  # the query's features (``query`` is their dict), for later steps

    def query_at(self, k: int) -> dict | None:
        """The query's features at rotation ``k``, extracted now when the cascade screened turned tiles instead
        (or None without features)."""
        if self.features is not None and k < 2 * DIAGONAL:
            return self.features(k)
        return self.query.get(k)


def _by_screen(c: Candidate) -> tuple:
    """Screened candidates, best screen first; ties keep the retrieval order."""
    return (-c.screen, c.retrieval_rank)


def _rank(c: Candidate) -> tuple:
    """The cascade's order: matcher-verified candidates by inliers, then screened ones by screen inliers, then the
    unvisited in retrieval order."""
    return (c.inliers < 0, -c.inliers, c.screen < 0, -c.screen, c.retrieval_rank)


def mutual_nn(d0: np.ndarray, d1: np.ndarray, min_sim: float = 0.0) -> np.ndarray:
    """(M, 2) index pairs of mutual nearest neighbours (cosine similarity above ``min_sim``)."""
    from aeroloc.matching.models.xfeat import mutual_nn as mnn

    return mnn(d0, d1, min_sim)[0]


def turn_score_pairs(probe: list[Candidate], cands: list[Candidate], turn_scores: dict) -> list:
    """(candidate, rotation) pairs in the order to screen a photo of unknown heading: the ``probe`` upright
    (most photos are near north-up, and over all turns the turned views of other places outscore a north-up
    photo's true tile), then every pair the turned retrieval scored (``turn_scores``: tile id -> {rotation:
    the query's global similarity to the tile at it}), best first; ties by retrieval rank, then rotation.
    Replayed on every candidate's screens at all eight turns (no priors), the pair that settles a heading comes
    at a median of 19 / 6 / 1 screens in this order on NAIP dev-rotated / levir-tx/any / szada-hu/any, against
    82 / 16 / 8 with the probe and then each candidate at its turns in retrieval order; on levir-tx/north, a
    north-up set, at 1 either way (README #13, "Screens in the order of the turned retrieval")."""
    first = [(c, 0) for c in probe]
    scored = sorted(
        (-s, c.retrieval_rank, k, c.tile_id)
        for c in cands
        for k, s in turn_scores.get(c.tile_id, {}).items()
        if k < 2 * DIAGONAL and not (k == 0 and c.retrieval_rank < len(probe))
    )
    by_id = {c.tile_id: c for c in cands}
    return first + [(by_id[t], k) for _, _, k, t in scored]


class Screens:
    """Screen results by (tile, rotation), each computed once: in the caller's order, or ahead of it on a second
    core. A screen is a pure function of its two feature sets (mutual nearest neighbours, then MAGSAC and RANSAC,
    which seed every call), so the order and the thread they are computed in change no result, only when it is
    ready; the cascade's own order decides which results are used, so a result computed ahead and not asked for
    is dropped. Without a ``pool`` every screen is computed on demand, in the caller's thread."""

    def __init__(self, screen_pair, pair, pool: ThreadPoolExecutor | None, cheap=None):
        self._screen_pair, self._pair, self._pool = screen_pair, pair, pool
        self._cheap = cheap or (lambda t, k: False)
        self._ahead: dict[tuple[str, int], Future] = {}
        self.asked: set[tuple[str, int]] = set()  # (tile, rotation) pairs the caller has had

    def ahead(self, pairs, guess: bool = False) -> None:
        """Start the screens of ``pairs`` ((tile id, rotation)) on the pool; their features (``pair(tile id,
        rotation) -> (query features, tile features)``) are got here first. With ``guess`` (screens the cascade
        may not ask for) only the pairs whose features are ``cheap`` (no query extraction), so a wrong guess
        costs the second core's time alone."""
        if self._pool is None:
            return
        for t, k in pairs:
            if (t, k) not in self._ahead and (t, k) not in self.asked and (not guess or self._cheap(t, k)):
                self._ahead[(t, k)] = self._pool.submit(self._screen_pair, *self._pair(t, k))

    def __call__(self, tile_id: str, k: int):
        """The screen of ``tile_id`` at rotation ``k``: (inliers, H, matches, visualisation)."""
        self.asked.add((tile_id, k))
        f = self._ahead.pop((tile_id, k), None)
        return f.result() if f is not None else self._screen_pair(*self._pair(tile_id, k))

    def close(self) -> None:
        """Drop the screens started ahead and not asked for (waiting for any still running: its core is the
        next stage's)."""
        for f in self._ahead.values():
            f.cancel()
        wait(list(self._ahead.values()))
        self._ahead.clear()


class QueryFeatures:
    """One query's local features per rotation (rot_k -> features) at one exact turn, each extracted once for
    the whole localization: every cascade over the same photo (the upright retrieval's tiles, then the turned
    retrieval's) shares them. ``seconds`` is the time spent extracting. Started ahead on the second core while
    retrieval describes the photo, the first rotation was measured and not adopted (levir-tx/any, rough priors,
    2 threads: the descriptor slowed from 81 to 131 ms beside it, 27 ms saved a query; no priors: the turned
    retrieval's descriptors slowed by ~250 ms, torch's second thread team on the same two cores)."""

    def __init__(self, extractor, image: np.ndarray, side: int, turn_deg: float = 0.0):
        self.image, self.turn_deg = image, float(turn_deg)
        self._extractor, self._side = extractor, side
        self.done: dict[int, dict] = {}
        self.seconds = 0.0

    def fits(self, image: np.ndarray, turn_deg: float) -> bool:
        return image is self.image and float(turn_deg) == self.turn_deg

    def _extract(self, key: int, k: int, turn_deg: float) -> dict:
        t = time.perf_counter()
        self.done[key] = extract(self._extractor, self.image, self._side, k, turn_deg=turn_deg)
        self.seconds += time.perf_counter() - t
        return self.done[key]

    def __call__(self, k: int) -> dict:
        """The features at rotation ``k`` (0-3 quarter turns, 4-7 diagonals)."""
        return self.done[k] if k in self.done else self._extract(k, k, self.turn_deg)

    def at_angle(self, turn_deg: float) -> int:
        """Extract the query at the exact turn ``turn_deg`` (no rotation) and return the key it is kept under:
        past the rotation indices, so a rotation never reads it."""
        key = 2 * DIAGONAL + len(self.done)
        self._extract(key, 0, turn_deg)
        return key


class Reranker:
    """Holds the extractor/matcher and the tile feature store of one database."""

    def __init__(self, db, name: str, device="cpu", conf: dict | None = None):
        from aeroloc.matching.features import store_for, turn_store_for

        self.db, self.name = db, name
        self.conf = rerank_conf(name, conf)
        self.extractor, self.matcher = build_reranker(self.conf["features"], device, feature_overrides(self.conf))
        self.store = store_for(db, name, self.conf)
        self._have = self.store.names()
        self.turns = turn_store_for(self.store) if self.conf.get("turned_tiles", True) else None
        self._turned = self.turns.names() if self.turns is not None else set()  # tiles held at every turn
        self._turns_open = None  # the turned store's open reader (_turn_reader)
        self._orientation: dict[str, float] = {}
        self._tile_cache: OrderedDict[str, dict] = OrderedDict()  # tile id -> decoded features (tile_features)
        self._pool: ThreadPoolExecutor | None = None
        self._pool_size = 0

    def _screen_pool(self) -> ThreadPoolExecutor | None:
        """The threads screens run on ahead of the cascade's order (:class:`Screens`): the conf's
        ``screen_threads``, else torch's thread count (what ``OMP_NUM_THREADS`` allows this process), at most 2;
        None for one. The pool is kept for the re-ranker's life."""
        n = self.conf.get("screen_threads")
        if n is None:
            import torch

            n = min(2, torch.get_num_threads())
        n = int(n)
        if n <= 1:
            return None
        if self._pool is None or self._pool_size != n:
            self._pool, self._pool_size = ThreadPoolExecutor(n, thread_name_prefix="aeroloc-screen"), n
        return self._pool

    def tile_features(self, tile_ids: list[str], turn: int = 0) -> dict[str, dict]:
        """From the store; tiles not there yet are extracted once and written (lazy cache). ``turn``: the tiles
        at that rotation index, from the turned tile store (only tiles it holds). The last ``tile_cache`` feature
        sets read are kept decoded: a store read costs ~1.4 ms a tile in h5py's per-dataset overhead (28 ms for
        a query's 20 candidates), and consecutive photos of a flight or a survey share most of their candidates.
        Callers never modify what they get."""
        missing = [t for t in tile_ids if t not in self._have] if not turn else []
        if missing:
            new = {t: extract(self.extractor, self.db.tile_image(t), self.conf["tile_side"]) for t in missing}
            self.store.write_many(new)
            self._have |= set(missing)
        names = {t: turned_name(t, turn) if turn else t for t in tile_ids}
        cache, size = self._tile_cache, self.conf["tile_cache"]
        to_read = [n for n in dict.fromkeys(names.values()) if n not in cache]
        if to_read and turn:
            for n in to_read:
                cache[n] = self._turn_reader().get(n)
        elif to_read:
            with self.store.reader() as r:
                for n in to_read:
                    cache[n] = r.get(n)
        out = {t: cache[names[t]] for t in tile_ids}
        for n in names.values():
            cache.move_to_end(n)
        while len(cache) > max(size, len(out)):  # at least this call's tiles, whatever the size
            cache.popitem(last=False)
        return out

    def _turn_reader(self):
        """The turned tile store's reader, kept open for the re-ranker's life: turned tiles are read one at a
        time as the screens ask for them, and opening a shard file costs as much as reading a tile (~1 ms)."""
        if self._turns_open is None:
            self._turns_open = self.turns.reader().__enter__()
        return self._turns_open

    def _turned_tile_screens(self, query: QueryFeatures, k: int, tile_id: str) -> bool:
        """Whether the screen of ``tile_id`` at rotation ``k`` takes the upright query against the turned tile
        (:meth:`_pair`): a turn other than upright, the query at no exact turn, the tile in the turned store."""
        return 0 < k < 2 * DIAGONAL and not query.turn_deg and tile_id in self._turned

    def _pair(
        self, query: QueryFeatures, k: int, tile_id: str, tfs: dict | None = None, screen: bool = False
    ) -> tuple[dict, dict]:
        """(query features, tile features) that screen (``screen``) or match ``tile_id`` with the query at rotation
        ``k``. A screen takes the upright query against the tile turned back
        (:func:`~aeroloc.matching.features.inverse_turn`) when the turned tile store holds it and the query is at
        no exact turn, so a photo of unknown heading is extracted once for its screens; else, and always for the
        matcher, the query at ``k`` (extracted on first use) against the upright tile. LighterGlue found fewer
        inliers on turned tiles (NAIP dev-rotated: 141 -> 105, 96 -> 84, 96 -> 29 on a diagonal), the screen
        about as many. Either way the transform relates the original images
        (:func:`~aeroloc.matching.features.to_original`)."""
        if screen and self._turned_tile_screens(query, k, tile_id):
            return query(0), self.tile_features([tile_id], inverse_turn(k))[tile_id]
        qf = query(k) if k < 2 * DIAGONAL else query.done[k]
        return qf, tfs[tile_id] if tfs is not None and tile_id in tfs else self.tile_features([tile_id])[tile_id]

    def match_at(self, query: QueryFeatures, c: Candidate):
        """The matcher on candidate ``c`` at its rotation (what :meth:`match_pair` returns)."""
        return self.match_pair(*self._pair(query, c.rot_k, c.tile_id))

    def doubt(self, c: Candidate) -> str | None:
        """Why the best candidate must not be trusted, or None. A learned matcher can find ~40 consistent matches
        on a wrong tile of similar texture; the screen's independent count then stays low (<= 20), whereas on
        the right tile one of the two is high."""
        if not self.conf["screen"] or c.inliers < 0:
            return None  # screen-only candidate (or no screen at all): min_inliers alone decides
        if c.screen < self.conf["min_screen"] and c.inliers < self.conf["confident_inliers"]:
            return (
                f"screen found {c.screen} inliers < {self.conf['min_screen']} and the matcher {c.inliers} "
                f"< {self.conf['confident_inliers']}"
            )
        return None

    def _verify(self, qf: dict, tf: dict, matches: np.ndarray, geometry: str = "homography", fallback: bool = True):
        """(inliers, transform, matches, (query kpts, tile kpts, inlier mask)) of ``geometry``; an insane homography
        is replaced by the similarity refitted on the same matches, or, without ``fallback`` (the caller has
        that similarity already), counts nothing."""
        from aeroloc.matching.verify import homography_is_sane, verify_homography, verify_similarity

        if len(matches) < 4:
            return 0, None, len(matches), None
        k0, k1 = to_original(qf), to_original(tf)
        thr = self.conf["ransac_px"] / float(tf["scale"])
        if geometry == "similarity":
            v = verify_similarity(k0, k1, matches, threshold_px=thr)
        else:
            v = verify_homography(k0, k1, matches, threshold_px=thr)
            if v.H is not None and not homography_is_sane(v.H, tuple(int(x) for x in qf["orig_size"]))[0]:
                if not fallback:
                    return 0, None, len(matches), None
                # nadir imagery: a full homography fitted on clustered inliers can extrapolate wildly; refit the
                # better-conditioned similarity model (rotation, scale, shift) and count its own inliers
                v = verify_similarity(k0, k1, matches, threshold_px=thr)
        H, inliers = v.H, np.asarray(v.inliers, bool)
        vis = (k0[matches[:, 0]], k1[matches[:, 1]], inliers)
        return int(inliers.sum()), H, len(matches), vis

    def screen_pair(self, qf, tf):
        """The screen: mutual nearest neighbours + RANSAC of ``screen_geometry`` (its inliers are what the thresholds
        count); with ``screen_fit`` "similarity" the transform kept is the similarity refitted on those inliers
        (aeroloc.matching.verify.similarity_on_inliers), what a screen-only fix is placed with."""
        from aeroloc.matching.verify import similarity_on_inliers

        matches = mutual_nn(qf["descriptors"], tf["descriptors"], self.conf["screen_min_sim"])
        n, H, n_matches, vis = self._verify(qf, tf, matches, self.conf["screen_geometry"])
        also = self.conf["screen_homography_min"]
        if self.conf["screen_geometry"] == "similarity" and also is not None and n >= also:
            # a strong pair of a tilted photo: its homography may hold more inliers (counts the thresholds know)
            more = self._verify(qf, tf, matches, "homography", fallback=False)  # insane: the similarity stands
            if more[0] > n:
                n, H, n_matches, vis = more
        if H is not None and vis is not None and n >= 2 and self.conf["screen_fit"] == "similarity":
            k0, k1, inliers = vis
            refit = similarity_on_inliers(k0[inliers], k1[inliers])
            H = refit if refit is not None else H
        return n, H, n_matches, vis

    def match_pair(self, qf, tf):
        matches, _ = self.matcher.match(qf, tf)
        return self._verify(qf, tf, np.asarray(matches, np.int64).reshape(-1, 2), self.conf["geometry"])

    def match_window(self, qf: dict, window, ref_tile) -> tuple:
        """Match query features against a map window (aeroloc.localization.window.Window) described at the working scale of
        the database's tiles (``ref_tile``); returns what :meth:`match_pair` does."""
        side = round(max(window.image.shape[:2]) * self.conf["tile_side"] / max(ref_tile.width, ref_tile.height))
        wf = extract(self.extractor, window.image, side, 0, mask=window.valid)
        return self.match_pair(qf, wf)

    def tile_orientation(self, tile_id: str) -> float:
        """The tile's dominant orientation (aeroloc.matching.orientation), computed once per tile and kept."""
        from aeroloc.matching.orientation import dominant_orientation

        a = self._orientation.get(tile_id)
        if a is None:
            a = self._orientation[tile_id] = dominant_orientation(self.db.tile_image(tile_id))[0]
        return a

    def _families(self, image: np.ndarray):
        """A function: tile id -> the rotations to screen it at when the heading is unknown: the quarter turns,
        and the diagonals (4-7) before them when the query's cross lies nearer 45° than 0° off the tile's
        (aeroloc.matching.orientation). Later candidates, while the heading is not settled, are screened at
        their own list: the diagonals are added, never traded for a quarter turn (screening only the estimated
        family lost a szada-hu query whose tile's cross was 35° off its true turn). Orientations are computed
        on first use, so a photo settled at the upright turn reads no tile image for them."""
        from aeroloc.matching.orientation import dominant_orientation, residual_turn

        quarter, diagonal = [0, 1, 2, 3], [DIAGONAL + k for k in range(4)]
        query: list[float] = []

        def family(tile_id: str) -> list[int]:
            if not query:
                query.append(dominant_orientation(image)[0])
            diag = abs(residual_turn(query[0], self.tile_orientation(tile_id))) > 22.5
            return diagonal + quarter if diag else quarter

        return family

    def _screen(
        self,
        cands: list[Candidate],
        rots: list[int],
        screens: Screens,
        families=None,
        turn_scores=None,
        own_angle=None,
    ) -> int:
        """Stage 1 in place on ``cands``; returns the number of (candidate, rotation) pairs screened.

        Rotation-major on the first ``rotation_probe`` candidates: all of them at the upright rotation first, the
        next rotation only if none reached ``min_screen``; later candidates at the heading found (or at every
        rotation while none is). Stops at the first candidate reaching ``early_exit``, after screening the next
        ``after_exit`` unvisited candidates at its turn (:meth:`_after_exit`). With ``families`` (tile
        id -> its rotations, :meth:`_families`; the heading unknown) the probe tries all eight rotations, and a
        later candidate, while the heading is not settled, its own list. ``screens`` computes them (ahead of this
        order on a second core where the process has one: the probe's candidates at a rotation together, and the
        next candidate at the settled rotation while one is screened). With ``turn_scores`` too (the retrieval's
        similarity per tile and turn) the first ``turn_score_screens`` pairs in :func:`turn_score_pairs`' order
        go first, until one settles a heading; ``own_angle`` (candidate -> the key of the query turned by its
        screen's own angle, or None) then screens the settling candidate again at its own angle, and every
        candidate is screened at the better of the two. The loop below runs only when none settled a heading,
        and never screens a pair twice.
        """
        c_ = self.conf
        best = {"rot": rots[0], "score": -1}
        n = 0

        def screen(c: Candidate, k: int) -> bool:
            nonlocal n
            if (c.tile_id, k) in screens.asked:  # screened in the turn-score order already (it did not exit)
                return False
            c.take(*screens(c.tile_id, k), k, "screen")
            n += 1
            if c.screen > best["score"] and c.rot_k == k:
                best.update(rot=k, score=c.screen)
            return c.screen >= c_["early_exit"]

        probe, rest = cands[: max(1, c_["rotation_probe"])], cands[max(1, c_["rotation_probe"]) :]
        if families is not None and turn_scores and c_["turn_score_screens"]:
            ordered = turn_score_pairs(probe, cands, turn_scores)[: c_["turn_score_screens"]]
            for i, (c, k) in enumerate(ordered):
                screens.ahead(((d.tile_id, j) for d, j in ordered[i : i + 2]), guess=True)
                if screen(c, k):
                    return n + self._after_exit(cands, k, screens, at_turn=True)
                if best["score"] >= c_["min_screen"]:  # the heading settled: every candidate at its turn
                    key = own_angle(c) if own_angle is not None else None
                    if key is not None and screen(c, key):  # the query turned as the settling screen says
                        return n + self._after_exit(cands, key, screens, at_turn=True)
                    k = best["rot"]
                    tail = [d for d in cands if (d.tile_id, k) not in screens.asked]
                    for j, d in enumerate(tail):
                        screens.ahead((e.tile_id, k) for e in tail[j : j + 2])
                        if screen(d, k):
                            return n + self._after_exit(cands, k, screens, at_turn=True)
                    return n

        def probe_order():
            # every rotation on the probe, the first candidate's family first, but upright first of all: most
            # photos are near north-up, and then it costs one extraction
            yield 0
            first = families(probe[0].tile_id)
            yield from [r for r in first if r != 0] + [r for r in range(2 * DIAGONAL) if r not in first]

        order = list(probe_order() if families else rots)
        for i, k in enumerate(order):
            screens.ahead((c.tile_id, k) for c in probe)
            if i:  # past the upright turn (most photos settle there): the next turn's probe on the second core
                screens.ahead(((c.tile_id, k2) for k2 in order[i + 1 : i + 2] for c in probe), guess=True)
            # every probe candidate at k, even after one exits early there (its screen was started ahead): a
            # candidate already screened at another turn is not "unvisited" for _after_exit, so a short-circuit
            # here left the true tile unscreened at the turn that fits it (szada_any_0_05: a doubled field ranked
            # first exited at 40, the true tile next to it was never screened at that turn, where it scores 82)
            exits = [screen(c, k) for c in probe]
            if any(exits):
                return n + self._after_exit(cands, k, screens)
            if best["score"] >= c_["min_screen"]:
                break
        for i, c in enumerate(rest):
            settled = best["score"] >= c_["min_screen"]
            own = families(c.tile_id) if families and not settled else rots  # settled: its turn alone
            turns = [best["rot"]] + [r for r in own if r != best["rot"]]
            if settled:  # this candidate and the next at the settled turn: the next is what the loop asks for
                screens.ahead((r.tile_id, best["rot"]) for r in rest[i : i + 2])
            else:  # its turns, until one settles the heading
                screens.ahead(((c.tile_id, k) for k in turns), guess=True)
            for k in turns:
                if k != best["rot"] and best["score"] >= c_["min_screen"]:
                    break  # the heading is settled
                if screen(c, k):
                    return n + self._after_exit(cands, k, screens)
        return n

    def _after_exit(self, cands: list[Candidate], k: int, screens: Screens, at_turn: bool = False) -> int:
        """After an early exit at rotation ``k``: the next ``after_exit`` unvisited candidates (retrieval order)
        screened at ``k``, so that a repeated place ranked after the first strong one can still rival it
        (aeroloc.localization.localizer.Localizer._rival) or beat it. On szada-hu/any (rough priors) a forest
        edge 546 m from the truth screened 45-55 inliers at retrieval rank 1-3 and ended the screen; the true
        tiles, at ranks 2-10, screened 30-67. ``at_turn``: the next candidates not screened at ``k`` yet, visited
        or not (after the turn-score order, which visits candidates at other turns first). Returns the number
        screened."""
        fresh = (lambda c: (c.tile_id, k) not in screens.asked) if at_turn else (lambda c: c.screen < 0)
        more = [c for c in cands if fresh(c)][: self.conf["after_exit"]]
        screens.ahead((c.tile_id, k) for c in more)
        for c in more:
            c.take(*screens(c.tile_id, k), k, "screen")
        return len(more)

    def _screen_angle(self, c: Candidate, turn_deg: float) -> float | None:
        """The OpenCV angle that turns the query map-aligned by ``c``'s screen transform, when its screen settled
        a heading (``min_screen``) and that angle lies ``screen_turn_min_deg`` or more off the turn it was
        screened at (:meth:`_left_turn`); else None. levir-tx/any, no prior: levir_any_4_06 looks 65°, its true
        tile screened 25 inliers at the 90° turn and the matcher 3 there (25° of residual turn)."""
        return self._left_turn(c, turn_deg) if c.screen >= self.conf["min_screen"] else None

    def _left_turn(self, c: Candidate, turn_deg: float) -> float | None:
        """The OpenCV angle that turns the query map-aligned by ``c``'s screen transform, when it lies
        ``screen_turn_min_deg`` or more off the turn ``c`` was screened at (``turn_deg`` + its rotation); None
        without a transform, for a candidate screened at an exact angle already, or nearer than that."""
        from aeroloc.localization.structure_refine import placement_of

        if c.H is None or c.rot_k >= 2 * DIAGONAL:
            return None
        angle = placement_of(c.H)[0]
        if not np.isfinite(angle) or turn_gap(angle - float(turn_deg), c.rot_k) < self.conf["screen_turn_min_deg"]:
            return None
        return angle

    def query_features(self, image: np.ndarray, turn_deg: float = 0.0) -> QueryFeatures:
        """A photo's features for this re-ranker at ``turn_deg``, to share between its cascades."""
        return QueryFeatures(self.extractor, image, self.conf["query_side"], turn_deg)

    def _passes(self, c: Candidate) -> bool:
        """Whether the matcher verified ``c`` (``min_inliers``) and nothing casts doubt on it."""
        return c.inliers >= self.conf["min_inliers"] and self.doubt(c) is None

    def _own_angle(self, query: QueryFeatures, c: Candidate, keys: dict[float, int]) -> int | None:
        """The key of the query's features turned by ``c``'s own screen angle (the turn its screen transform
        says is left), extracted on first use; angles within ``screen_turn_min_deg`` of one in ``keys`` (angle
        -> key, updated) share its extraction. None when ``c`` has no screen transform or its angle lies within
        ``screen_turn_min_deg`` of the turn it was screened at: there the screen already saw the query at its
        own angle."""
        angle = self._left_turn(c, query.turn_deg)
        if angle is None:
            return None
        near = [k for a, k in keys.items() if turn_gap(angle - a, 0) < self.conf["screen_turn_min_deg"]]
        return near[0] if near else keys.setdefault(angle, query.at_angle(angle))

    def screen_is_noise(self, query: QueryFeatures, c: Candidate) -> bool:
        """Whether ``c``'s screen stays below ``min_screen`` (the count no wrong tile passed on NAIP and Toledo,
        and what settles a heading) with the query at ``c``'s own screen angle: screened there again when its
        screen left a turn of ``screen_turn_min_deg`` or more. Such a tile shows nothing of the query that a
        wrong tile does not, so the matcher is not run on it to rule it out as a rival. Logged over every set and
        prior mode (738 localizations): the 46 far tiles the rival check matched with screens 9-19 got 0-22 matcher
        inliers, never half the best's; the real rivals (szada-hu's repeated fields) screened 29-61. Re-screened at
        their own angle, wrong tiles screened 11-19 fell to 6-13 (NAIP dev-rotated, levir-tx/any, szada-hu/any, no
        priors), while right ones mostly rose (e.g. 22 -> 55, 16 -> 54), so the re-screen keeps a weakly seen true
        place in the check (README #13, "A far tile screened at noise level is no rival")."""
        floor = self.conf["min_screen"]
        if c.screen >= floor:
            return False
        self._rescreen(query, c)
        return c.screen < floor

    def _rescreen(self, query: QueryFeatures, c: Candidate) -> bool:
        """``c`` screened again with the query turned by its own screen angle (:meth:`_own_angle`), keeping the
        better screen and its transform (at the key of the turned query's features); False when there is no
        such angle to try."""
        key = self._own_angle(query, c, {})
        if key is None:
            return False
        c.take(*self.screen_pair(query.done[key], self.tile_features([c.tile_id])[c.tile_id]), key, "screen")
        return True

    def _screen_accepts(self, screened: list[Candidate], size: tuple[int, int]) -> bool:
        """Whether the screens (``screened``, best first) settle the query without the matcher: the best reaches
        ``accept_screen``, or another tile sees the same place and no far place comes close (agreement,
        aeroloc.localization.agreement)."""
        accept = self.conf["accept_screen"]
        if screened and accept is not None and screened[0].screen >= accept:
            return True
        return screen_agreed(self.db, screened, size, self.conf)

    def _rescreen_at_own_angle(self, query: QueryFeatures, c: Candidate | None) -> bool:
        """The best screened candidate ``c``, screened with ``min_screen`` or more but not accepted (its heading
        settled, the matcher would be asked), screened again with the query turned by its own screen angle
        (``own_angle_rescreen``), when that angle lies ``screen_turn_min_deg`` or more off the turn screened;
        ``c`` takes the re-screen (its transform, at the key of the turned query's features) when it is the
        better one, and the usual screen rules judge it again. True when it was re-screened. A query between
        two of the turns tried screens its true tile weakly; at its own angle the screen doubles (NAIP
        dev-rotated, no priors: 22 -> 55, 24 -> 56, 29 -> 51; levir-tx/any 27 -> 55, 21 -> 54), while wrong
        tiles fall (11-19 -> 6-13): ~80 ms (one extraction) against the matcher's ~400."""
        if c is None or not self.conf["own_angle_rescreen"]:
            return False
        accept = self.conf["accept_screen"]
        if c.screen < self.conf["min_screen"] or (accept is not None and c.screen >= accept):
            return False
        return self._rescreen(query, c)

    def weak_screen_turns(self, rr: Reranked) -> bool:
        """After a cascade (and the localizer's window re-alignments) found nothing: the best
        ``weak_screen_turns`` screened candidates of ``rr`` (at least ``weak_screen_min`` inliers, below what
        settles a heading) screened again with the query turned by their own screen's angle, and those reaching
        ``min_screen`` there matched at it, until one passes; ``rr`` re-ordered in place (its times added). True
        when one passed. A query halfway between two of the turns tried (20-25° off both) screens weakly on its
        true tile, but that weak screen's transform holds the turn left: szada_any_5_04 (20° heading, no prior)
        screened 18-19 on its two true tiles at 45°, and 49 and 39 with the query turned by their own 19.8° and
        20.1° (the matcher then 119 on one); the wrong tiles it screened 12-22 stayed at 7-16 at their own angles.
        The re-screen counts as the candidate's screen and the usual rules accept the result. Angles within
        ``screen_turn_min_deg`` of each other share one extraction."""
        c_, query = self.conf, rr.features
        if not (c_["screen"] and c_["max_verify"] and c_.get("weak_screen_turns", 0)) or query is None:
            return False
        t0, seconds0 = time.perf_counter(), query.seconds
        floor, settle = c_["weak_screen_min"], c_["min_screen"]
        weak = sorted(
            (c for c in rr.ranked if floor <= c.screen < settle and c.rot_k < 2 * DIAGONAL and c.H is not None),
            key=_by_screen,
        )[: c_["weak_screen_turns"]]
        tfs = self.tile_features([c.tile_id for c in weak])
        keys: dict[float, int] = {}  # angle -> the query features' key at it
        passed = False
        for c in weak:
            key = self._own_angle(query, c, keys)
            if key is None:
                continue
            c.take(*self.screen_pair(query.done[key], tfs[c.tile_id]), key, "screen")
            rr.n_screened += 1
            if c.screen < settle or c.rot_k != key:
                continue
            c.take(*self.match_pair(query.done[key], tfs[c.tile_id]), key, "verify")
            rr.n_verified += 1
            if self._passes(c):
                passed = True
                break
        rr.ranked.sort(key=_rank)
        rr.candidates = rr.ranked[: len(rr.candidates)]
        extract_ms = (query.seconds - seconds0) * 1000
        rr.times_ms["local_features"] = rr.times_ms.get("local_features", 0.0) + extract_ms
        rr.times_ms["rerank"] = rr.times_ms.get("rerank", 0.0) + (time.perf_counter() - t0) * 1000 - extract_ms
        return passed

    def __call__(
        self,
        image: np.ndarray,
        tile_ids: list[str],
        top_k: int = 1,
        rotations=None,
        turn_deg: float = 0.0,
        query: QueryFeatures | None = None,
        turn_scores: dict[str, dict[int, float]] | None = None,
    ) -> Reranked:
        """Re-rank ``tile_ids`` for ``image``; ``rotations`` (indices of aeroloc.matching.features.rotation_angle:
        0-3 quarter turns CCW, 4-7 diagonals) overrides the conf's, e.g. the one a heading prior points at;
        ``turn_deg`` (OpenCV degrees) turns the query exactly before them (a heading prior's own angle).
        ``query``: the photo's features extracted so far (:meth:`query_features`), used when it holds this image
        at this turn; otherwise each rotation is extracted on first use (an upright photo that matches costs one
        extraction). ``turn_scores`` (the retrieval's per-turn similarities, aeroloc.retrieval.retriever.Retrieval)
        order the screens of a photo of unknown heading (:func:`turn_score_pairs`). Transforms relate the original image whatever the turn."""
        t0 = time.perf_counter()
        tfs = self.tile_features(tile_ids)
        t_tiles = time.perf_counter() - t0  # tile features (store reads); query extraction is added below
        cands = [Candidate(t, i) for i, t in enumerate(tile_ids)]
        rots = [k % 8 for k in (self.conf["rotations"] if rotations is None else rotations)]
        n_screened = n_verified = 0
        if query is None or not query.fits(image, turn_deg):
            query = self.query_features(image, turn_deg)
        seconds0 = query.seconds

        if self.conf["screen"]:
            unknown = rotations is None and not turn_deg and self.conf["diagonals"] and sorted(rots) == [0, 1, 2, 3]
            families = self._families(image) if unknown and cands else None
            screens = Screens(
                self.screen_pair,
                lambda t, k: self._pair(query, k, t, tfs, screen=True),
                self._screen_pool(),
                lambda t, k: k in query.done or self._turned_tile_screens(query, k, t),
            )
            try:
                own = (lambda c: self._own_angle(query, c, {})) if self.conf["own_angle_rescreen"] else None
                n_screened = self._screen(cands, rots, screens, families, turn_scores, own)
            finally:
                screens.close()
            screened = sorted((c for c in cands if c.screen >= 0), key=_by_screen)
            size = (image.shape[1], image.shape[0])
            if self._screen_accepts(screened, size):
                screened = []  # verified by the screen alone: the matcher would only cost time
            elif self._rescreen_at_own_angle(query, screened[0] if screened else None):
                n_screened += 1
                screened.sort(key=_by_screen)
                if self._screen_accepts(screened, size):
                    screened = []
            # with the heading unknown, a screen below the weak floor is noise: the matcher never made such a
            # candidate pass (96 runs on screens of 8-11), so it is not paid for (README #13, "Matcher runs that
            # could never pass"). With a heading known (a prior, --north-up) the screens are at the right turn and
            # the matcher's runs are bounded by max_verify; there a weak screen can still pass: the demo's
            # naip_20100629_n_018 (256 px tiles, --north-up) screened 11 on its true tile, the matcher found 51
            floor = self.conf["weak_screen_min"] if families is not None else 0
            to_verify = [(c, [c.rot_k]) for c in screened[: self.conf["max_verify"]] if c.screen >= floor]
            until_pass = True
        else:  # the straightforward loop: the matcher on every candidate x rotation
            to_verify, until_pass = [(c, rots) for c in cands], False
        turns_left = self.conf.get("screen_turns", 0)
        for c, ks in to_verify:
            screen_angle = self._screen_angle(c, turn_deg)
            for k in ks:
                c.take(*self.match_pair(*self._pair(query, k, c.tile_id, tfs)), k, "verify")
                n_verified += 1
            if until_pass and screen_angle is not None and turns_left > 0 and c.inliers < self.conf["min_inliers"]:
                # the screen placed this tile at a turn the matcher could not bridge: match at the screen's own
                key = query.at_angle(screen_angle)
                c.take(*self.match_pair(query.done[key], tfs[c.tile_id]), key, "verify")
                n_verified += 1
                turns_left -= 1
            if until_pass and self._passes(c):
                break
        order = sorted(cands, key=_rank)
        total = time.perf_counter() - t0
        t_extract = t_tiles + query.seconds - seconds0
        return Reranked(
            order[:top_k] if top_k else order,
            {"local_features": t_extract * 1000, "rerank": (total - t_extract) * 1000},
            n_screened,
            n_verified,
            query.done,
            order,
            query,
        )
