"""The frame's pose on the map, carried from fix to fix: where its centre is, how it is turned, how large a
frame pixel is on the ground.

A pose is the similarity frame px -> map px. A global fix gives it (the dense stage's turn and scale, or the
local-feature homography's rotation and scale at the frame centre); odometry steps compose onto it; windowed
fixes correct it. Its scale times the map's resolution is the frame's ground resolution and its turn the frame's
heading, so frames without metadata get the dense stage (self-calibration). Height above ground and heading drift
slowly, so a windowed fix's refined turn and scale are blended in rather than replacing the pose.

Turns follow the project's convention (the query sets' ``heading_deg``, the dense stage's angle): degrees the
frame's content is turned clockwise from the north-up map; the compass bearing the top of the frame points to
(``yaw_deg``) is read off the pose's geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Pose:
    x: float  # frame centre, map px
    y: float
    turn_deg: float
    scale: float  # map px per frame px

    def matrix(self, size: tuple[int, int]) -> np.ndarray:
        """3x3: frame px (pixel-edge origin, ``size`` = (w, h)) -> map px."""
        t = math.radians(self.turn_deg)
        R = np.array([[math.cos(t), math.sin(t)], [-math.sin(t), math.cos(t)]]) * self.scale
        c = np.array([size[0] / 2.0, size[1] / 2.0])
        M = np.eye(3)
        M[:2, :2], M[:2, 2] = R, np.array([self.x, self.y]) - R @ c
        return M

    @classmethod
    def from_matrix(cls, M: np.ndarray, size: tuple[int, int]) -> Pose:
        c = M[:2, :2] @ np.array([size[0] / 2.0, size[1] / 2.0]) + M[:2, 2]
        J = M[:2, :2]
        s = math.sqrt(abs(float(np.linalg.det(J))))
        t = math.degrees(math.atan2(-J[1, 0], J[0, 0]))
        return cls(float(c[0]), float(c[1]), t, s)

    def moved(self, A: np.ndarray, size: tuple[int, int]) -> Pose:
        """The pose of the next frame, ``A`` (2x3) mapping its pixels to this frame's."""
        step = np.vstack([A, [0, 0, 1]])
        return Pose.from_matrix(self.matrix(size) @ step, size)

    def yaw_deg(self) -> float:
        """Compass bearing of the frame's top: its up vector on the map (map rows grow southwards)."""
        t = math.radians(self.turn_deg)
        east, south = -math.sin(t), -math.cos(t)
        return math.degrees(math.atan2(east, -south)) % 360.0

    def gsd_m(self, map_gsd: float) -> float:
        return self.scale * map_gsd

    def footprint(self, size: tuple[int, int]) -> np.ndarray:
        w, h = size
        M = self.matrix(size)
        return (np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], float) @ M.T)[:, :2]


def pose_from_homography(H: np.ndarray, size: tuple[int, int], tile_col: float, tile_row: float) -> Pose | None:
    """The similarity nearest ``H`` (frame px -> tile px) at the frame centre, shifted into map px; None for a
    mirrored or degenerate local map."""
    w, h = size
    pts = np.array([[w / 2, h / 2, 1], [w / 2 + 1, h / 2, 1], [w / 2, h / 2 + 1, 1]], float) @ H.T
    if np.any(np.abs(pts[:, 2]) < 1e-9):
        return None
    xy = pts[:, :2] / pts[:, 2:]
    J = np.stack([xy[1] - xy[0], xy[2] - xy[0]], axis=1)
    det = float(np.linalg.det(J))
    if not math.isfinite(det) or det <= 0:
        return None
    # nearest rotation-and-scale: average the two columns' rotation
    a, b = (J[0, 0] + J[1, 1]) / 2, (J[0, 1] - J[1, 0]) / 2
    return Pose(
        float(xy[0, 0] + tile_col), float(xy[0, 1] + tile_row), math.degrees(math.atan2(b, a)), math.hypot(a, b)
    )


def pose_from_dense(d, map_gsd: float) -> Pose:
    """A dense-stage answer (aeroloc.localization.dense_stage.DenseResult) as a pose."""
    return Pose(d.col, d.row, float(d.match.angle), d.query_gsd * d.match.scale / map_gsd)


def turn_difference(d: float) -> float:
    """A difference of turns (degrees) in [-180, 180)."""
    return (d + 180.0) % 360.0 - 180.0


def blend(pose: Pose, x: float, y: float, turn: float | None, scale: float | None, k: float = 0.3) -> Pose:
    """``pose`` moved to (x, y), its turn and scale moved ``k`` of the way to a fix's."""
    t, s = pose.turn_deg, pose.scale
    if turn is not None:
        t += k * turn_difference(turn - t)
    if scale is not None:
        s *= (scale / s) ** k
    return Pose(x, y, t, s)


class BaselineScale:
    """The odometry's scale error, from long baselines: how far apart two good fixes lie on the map over how far
    the odometry chain moved between them. Without a height the scale is the product of every pair's scale
    change, and it drifts (NAIP: -1 % to -3 % over 180 frames, the steps 2 % short, 0.4 m a frame); fixes
    3-5 m off over >= ``min_m`` give it to ~1 %. A correction moves ``gain`` of the way, at most ``max_step``,
    and starts the next baseline afresh (the old one was measured at the old scale)."""

    def __init__(self, min_m: float = 400.0, gain: float = 0.3, max_step: float = 0.02):
        self.min_m, self.gain, self.max_step = min_m, gain, max_step
        self.odo = (0.0, 0.0)  # the chain's position, metres (odometry steps only)
        self.marks: list[tuple[tuple[float, float], tuple[float, float]]] = []  # (chain, fix) at good fixes
        self.checked = False  # a baseline found the scale within 2 % (until a global fix sets it anew)

    def moved(self, dx: float, dy: float) -> None:
        self.odo = (self.odo[0] + dx, self.odo[1] + dy)

    def broken(self) -> None:
        """The chain broke (coasting, a lost track): earlier marks no longer compare."""
        self.marks.clear()

    def fix(self, x: float, y: float) -> float | None:
        """Record a good fix (metres); the factor to multiply the scale by once a baseline is long enough."""
        for chain, f in reversed(self.marks):
            d_fix = math.hypot(x - f[0], y - f[1])
            if d_fix >= self.min_m:
                d_odo = math.hypot(self.odo[0] - chain[0], self.odo[1] - chain[1])
                self.marks = [(self.odo, (x, y))]
                if d_odo <= 0:
                    return None
                k = (d_fix / d_odo) ** self.gain
                self.checked = abs(d_fix / d_odo - 1) < 0.02
                return min(1 + self.max_step, max(1 - self.max_step, k))
        self.marks = self.marks[-63:] + [(self.odo, (x, y))]
        return None
