"""How to localize: one frozen, validated settings object for the CLI, the Python API and the benchmark.

Every check lives in :meth:`LocalizeOptions.__post_init__`, so a bad or contradictory setting fails once, with
one message, before any file is touched, wherever the options come from.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any

from aeroloc.core import provenance
from aeroloc.core.errors import AerolocError
from aeroloc.localization.dense_stage import check_query_gsd
from aeroloc.matching.registry import DEFAULT_RERANKER, rerank_conf
from aeroloc.retrieval.retriever import check_rotations


@dataclass(frozen=True)
class LocalizeOptions:
    """``top_n`` candidates retrieved, ``top_k`` kept after re-ranking (0 = all); ``method`` the retrieval method
    (None: the database's default); ``rerank`` the re-ranker (None: retrieval only, the best tile's centre);
    ``rerank_overrides`` of its cascade settings (aeroloc.matching.registry); ``rotations`` > 1 retrieves with the
    query at that many headings; ``north_up`` for queries known to be north-up within about ±45° (no 90° rotation
    search; the dense stage searches ±15°); ``query_gsd`` (metres per query pixel) turns the dense structural
    stage on; ``dense_overrides`` of its settings (aeroloc.matching.dense.DEFAULTS); ``sweep`` searches the whole
    map at every heading and scale the priors allow (aeroloc.localization.sweep_stage) for queries with priors,
    and for those the quarter-turn cascade could not place; ``sweep_overrides`` of its settings
    (aeroloc.matching.sweep.SWEEP_DEFAULTS); ``min_confidence`` the calibrated confidence a fix needs
    (aeroloc.localization.confidence); ``structure_refine`` moves local-feature fixes to the dense structure's
    peak at their own heading and scale when the two agree (aeroloc.localization.structure_refine);
    ``neighbours`` re-ranks the tiles beside the first retrieved ones when nothing else placed a query without
    priors, before the sweep (aeroloc.localization.neighbours); ``trim_canvas`` replaces a photo on a black canvas
    with the photo alone, turned back upright and cut to its centred window (aeroloc.core.canvas)."""

    top_n: int = 20
    top_k: int = 1
    method: str | None = None
    rerank: str | None = DEFAULT_RERANKER
    rerank_overrides: dict[str, Any] | None = field(default=None, hash=False)
    rotations: int = 1
    north_up: bool = False
    query_gsd: float | None = None
    dense_overrides: dict[str, Any] | None = field(default=None, hash=False)
    sweep: bool = True
    min_confidence: float = 0.5
    sweep_overrides: dict[str, Any] | None = field(default=None, hash=False)
    structure_refine: bool = True
    neighbours: bool = True
    trim_canvas: bool = True

    def __post_init__(self):
        if not isinstance(self.top_n, int) or self.top_n < 1:
            raise AerolocError(f"top-n must be an integer >= 1, got {self.top_n!r}")
        if not isinstance(self.top_k, int) or self.top_k < 0:
            raise AerolocError(f"top-k must be an integer >= 0 (0 = every candidate), got {self.top_k!r}")
        object.__setattr__(self, "rotations", check_rotations(self.rotations))
        if self.north_up and self.rotations != 1:
            raise AerolocError(
                f"--north-up and --rotations > 1 contradict each other: north-up queries need no rotation "
                f"search, but rotations={self.rotations} was asked for"
            )
        object.__setattr__(self, "query_gsd", check_query_gsd(self.query_gsd))
        if self.rerank in ("none", ""):
            object.__setattr__(self, "rerank", None)
        if self.rerank is not None:
            rerank_conf(self.rerank, self.rerank_overrides)  # unknown names and options fail here
        self.sweep_conf()  # unknown sweep settings fail here
        if not 0.0 <= self.min_confidence < 1.0:
            raise AerolocError(f"min-confidence must be in [0, 1), got {self.min_confidence!r}")
        if self.query_gsd is not None and self.rerank is None:
            raise AerolocError(
                "the dense stage (query ground resolution) needs a re-ranker; it is off with --rerank none"
            )

    def cascade_overrides(self) -> dict | None:
        """The re-ranker overrides in effect: north-up queries need no 90° rotation search, so one query
        extraction and no screens at wrong headings."""
        if not self.north_up:
            return self.rerank_overrides
        return {**(self.rerank_overrides or {}), "rotations": [0]}

    def cascade_conf(self) -> dict | None:
        """The re-ranker's full effective settings (None for retrieval only)."""
        return rerank_conf(self.rerank, self.cascade_overrides()) if self.rerank else None

    def dense_conf(self) -> dict:
        """The dense stage's settings in effect: headings around north when ``north_up``, else the full circle
        (a query's heading prior narrows them per query)."""
        from aeroloc.matching.dense import heading_angles

        return heading_angles(self.dense_overrides, self.north_up)

    def sweep_conf(self) -> dict:
        """The sweep's settings in effect: its search (aeroloc.matching.sweep) and its structural confirmation
        (aeroloc.localization.structure_check)."""
        from aeroloc.localization.structure_check import STRUCTURE_DEFAULTS
        from aeroloc.matching.sweep import SWEEP_DEFAULTS

        known = {**SWEEP_DEFAULTS, **STRUCTURE_DEFAULTS}
        unknown = set(self.sweep_overrides or {}) - set(known)
        if unknown:
            raise AerolocError(f"unknown sweep settings {sorted(unknown)}; known: {sorted(known)}")
        return {**known, **(self.sweep_overrides or {})}

    def signature(self, db, query_names: list[str], query_scale: float, priors: list[str] | None = None) -> str:
        """Everything a results file depends on, as a string: a run resumes or reuses a file only when equal.
        ``priors``: each query's priors described, when any query has some."""
        kw = dict(
            db=str(db.folder.resolve()),
            top_n=self.top_n,
            top_k=self.top_k,
            method=self.method,
            rerank=self.rerank,
            rerank_conf=self.cascade_conf(),
            global_=db.meta.get("global", {}).get(self.method or db.meta.get("default_method")),
            queries=query_names,
            query_scale=query_scale,
            # rotations only when searched, so the signature of an upright run stays as it was
            **({"rotations": self.rotations} if self.rotations != 1 else {}),
            **({"query_gsd": self.query_gsd, "dense": self.dense_conf()} if self.query_gsd is not None else {}),
            **({"priors": priors, "dense": self.dense_conf()} if priors else {}),
            **({"sweep": self.sweep_conf()} if self.sweep and self.rerank else {}),
            **({"min_confidence": self.min_confidence} if self.min_confidence != 0.5 else {}),
            **({"structure_refine": False} if not self.structure_refine else {}),
            **({"trim_canvas": False} if not self.trim_canvas else {}),
            code=code_identity(),
        )
        return json.dumps(kw, sort_keys=True, default=str)

    def describe(self) -> dict:
        return asdict(self)


def code_identity() -> str:
    """The identity of the code a localization's result depends on (aeroloc.core.provenance): a results file
    written by other code is neither resumed nor reused (a changed acceptance rule with unchanged settings had
    reused old fixes)."""
    return provenance.code_identity(provenance.LOCALIZATION_PACKAGES)
