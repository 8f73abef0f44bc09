"""A calibrated confidence and a position uncertainty for every fix (``confidence``, ``sigma_m``).

``confidence`` is the probability that the fix lies within ``t = max(5 m, 2 map px)`` of the truth (the radius
of Georef@t), from a logistic model of the evidence the fix rests on: which stage made it (the quarter-turn
cascade on tiles, the sweep confirmed by local features, the dense stage at a known resolution) and how many
verified inliers it has. ``sigma_m`` is a 1-sigma radius-per-axis model of the error: ``map px x s / sqrt(inliers
/ 100)`` per stage, fitted so that the median error equals the median of a 2-D normal's radial error.

Both are fitted by ``benchmarks/calibrate.py`` on every shared set (``experiments/atlas.yaml``), and its
reliability table is computed leaving each set out in turn (the model that scores a set never saw it). The
coefficients below are that script's output; rerun it after changing a stage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SOURCES = ("cascade", "sweep", "dense")


@dataclass(frozen=True)
class StageModel:
    """``P(within t) = 1 / (1 + exp(-(a + b * ln(inliers))))``; ``sigma_px`` the 1-sigma error in map px at 100
    inliers (it shrinks with the square root of the inliers, floored at half a map pixel)."""

    a: float
    b: float
    sigma_px: float

    def confidence(self, inliers: int) -> float:
        z = self.a + self.b * math.log(max(1, inliers))
        return 1.0 / (1.0 + math.exp(-z))

    def sigma_m(self, inliers: int, map_gsd: float) -> float:
        return map_gsd * max(0.5, self.sigma_px * math.sqrt(100.0 / max(1, inliers)))


# fitted by benchmarks/calibrate.py (see the module docstring); placeholders are refused by its test
MODELS: dict[str, StageModel] = {
    "cascade": StageModel(a=0.0, b=1.0, sigma_px=1.0),
    "sweep": StageModel(a=0.0, b=1.0, sigma_px=1.0),
    "dense": StageModel(a=0.0, b=1.0, sigma_px=1.0),
}
MIN_CONFIDENCE = 0.5  # a fix below this is reported "not localized"


def source_of(status: str) -> str:
    """The stage a localized result's ``status`` names."""
    if status.startswith("localized (sweep"):
        return "sweep"
    if status.startswith("localized (dense"):
        return "dense"
    return "cascade"


def assess(status: str, inliers: int, map_gsd: float, models: dict[str, StageModel] | None = None):
    """(confidence, sigma_m) of a localized result."""
    m = (models or MODELS)[source_of(status)]
    return m.confidence(inliers), m.sigma_m(inliers, map_gsd)
