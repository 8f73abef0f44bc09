"""A weak windowed fix checked by local features, and the frame's pose they measure.

A windowed fix is a structural correlation peak at ~240 working px (aeroloc.flight.window_fix): on changed or
plain ground its score is weak, and a weak fix pulls the track little and never turns the heading
(``TrackConfig.turn_fix_score``). On the levir-tx flight without metadata (seed 3) fixes scoring 0.26-0.31 lay
2.6-3.7 m from the truth for 13 frames while the track, carried on a heading 4° off and a ground resolution 4 %
small, stayed 5.0-5.4 m off (t = 5 m). Matched by local features (the frame turned to the fix's heading against the
map window it covers, as the sweep's confirmation does) the same frames held 81-143 inliers, 2.1-3.1 m from the
truth, in ~190 ms: an independent check of the peak, whose homography measures the heading and the ground
resolution as well as the position.
"""

from __future__ import annotations

import math

import numpy as np

from aeroloc.flight.calibration import Pose, pose_from_homography
from aeroloc.localization.sweep_stage import footprint_window, match_on_window
from aeroloc.matching.features import extract
from aeroloc.matching.sweep import Hypothesis


def confirmed_pose(
    reranker, map_, image: np.ndarray, fix, min_inliers: int, reach_px: float
) -> tuple[Pose | None, int]:
    """The frame's pose measured by local features around the windowed ``fix`` (x, y map px, turn_deg, scale),
    and the inliers found: the frame turned by the fix's turn against the map window the fix says it covers
    (aeroloc.localization.sweep_stage.match_on_window, screened from ``weak_screen_min``). None (with the
    inliers) when fewer than ``min_inliers`` hold or the measured centre lies farther than ``reach_px`` map px
    from the fix."""
    size = (image.shape[1], image.shape[0])
    window = footprint_window(map_, Hypothesis(fix.x, fix.y, fix.turn_deg, fix.scale, fix.score), size)
    if window is None:
        return None, 0
    qf = extract(reranker.extractor, image, int(reranker.conf["query_side"]), 0, turn_deg=float(fix.turn_deg))
    n, H = match_on_window(reranker, qf, window, fix.scale, size, reranker.conf["weak_screen_min"])
    if H is None or n < min_inliers:
        return None, n
    pose = pose_from_homography(H, size, window.tile.col, window.tile.row)
    if pose is None or math.hypot(pose.x - fix.x, pose.y - fix.y) > reach_px:
        return None, n
    return pose, n
