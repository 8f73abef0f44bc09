"""A calibrated confidence and a position uncertainty for every fix (``confidence``, ``sigma_m``).

``confidence`` is the probability that the fix lies within ``t = max(5 m, 2 map px)`` of the truth (the radius
of Georef@t), from a logistic model of the evidence the fix rests on: which stage made it (the quarter-turn
cascade on tiles, the sweep confirmed by local features, the dense stage at a known resolution) and how many
verified inliers it has. ``sigma_m`` is a 1-sigma per-axis model of the error, ``sigma0_m + sigma_px x map
px`` per stage (metres of the truth's own noise and co-registration plus a share of a map pixel), fitted so that
the median error is the median radial error of a 2-D normal (1.1774 sigma). A model in map pixels alone was
tried first: it stated 0.4 m on the 0.5 m levir-tx map (errors 1.3-1.8 m) and 10 m on 5 m NAIP (errors 4 m).

Both are fitted by ``benchmarks/calibrate.py`` on every shared set (``experiments/atlas.yaml``), and its
reliability table is computed leaving each set out in turn (the model that scores a set never saw it). The
coefficients below are that script's output; rerun it after changing a stage.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

SOURCES = ("cascade", "sweep", "structure", "dense")
_RATIO = re.compile(r"ratio ([0-9.]+|inf)")


@dataclass(frozen=True)
class StageModel:
    """``P(within t) = 1 / (1 + exp(-(a + b * ln(evidence))))``; 1-sigma error ``sigma0_m + sigma_px x map px``.
    The evidence is the verified inliers of a local-feature fix, the distinctness ratio of a structural one."""

    a: float
    b: float
    sigma0_m: float
    sigma_px: float

    def confidence(self, evidence: float) -> float:
        z = self.a + self.b * math.log(max(1.0, min(evidence, 1e6)))
        return 1.0 / (1.0 + math.exp(-z))

    def sigma_m(self, evidence: float, map_gsd: float) -> float:
        return max(0.25 * map_gsd, self.sigma0_m + self.sigma_px * map_gsd)


# fitted by benchmarks/calibrate.py on the atlas runs of 2026-12-02 (199 fixes, 19 query sets of 12; see README)
MODELS: dict[str, StageModel] = {
    "cascade": StageModel(a=2.759, b=0.0, sigma0_m=1.035, sigma_px=0.585),
    "sweep": StageModel(a=-6.524, b=2.414, sigma0_m=0.804, sigma_px=0.592),
    # 6 structural fixes in the atlas (all within t): a cautious fit; refit when more are measured
    "structure": StageModel(a=1.095, b=0.945, sigma0_m=2.664, sigma_px=0.792),
    # no dense-stage fix in the atlas (it runs only with --query-gsd): a neutral model, not a fitted one
    "dense": StageModel(a=2.0, b=0.0, sigma0_m=1.0, sigma_px=0.5),
}
MIN_CONFIDENCE = 0.5  # a fix below this is reported "not localized"


def source_of(status: str) -> str:
    """The stage a localized result's ``status`` names."""
    if status.startswith("localized (sweep") and "structure confirmed" in status:
        return "structure"
    if status.startswith("localized (sweep"):
        return "sweep"
    if status.startswith("localized (dense"):
        return "dense"
    return "cascade"


def evidence(status: str, inliers: int) -> float:
    """What a fix's confidence rests on: the distinctness ratio its status states for a structural (dense or
    sweep-structure) fix, its verified inliers otherwise."""
    if source_of(status) in ("structure", "dense"):
        m = _RATIO.search(status)
        return float(m.group(1)) if m else 1.0
    return float(inliers)


def assess(status: str, inliers: int, map_gsd: float, models: dict[str, StageModel] | None = None):
    """(confidence, sigma_m) of a localized result."""
    m = (models or MODELS)[source_of(status)]
    e = evidence(status, inliers)
    return m.confidence(e), m.sigma_m(e, map_gsd)
