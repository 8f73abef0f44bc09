"""One place for changing an image's frame (resizing) and for moving points between frames (homographies).

Every stage brings images to a working resolution: retrieval shrinks large queries to the tiles' size, local
features bring query and tile to a common side, the dense stage to a common ground resolution. They all resize
here, so a query is resampled the same way wherever it goes: area-averaged when shrinking, nearest for masks,
and linear or cubic when enlarging (what each stage was measured with).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

_ENLARGE = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}

DIAGONAL = 4  # rotation indices 4-7: the quarter turn (index - 4) and 45° more, counter-clockwise
# the turns a turned store holds (aeroloc build --local-turns / --global-turns): 0, the upright tile, is the store
TILE_TURNS = tuple(range(1, 2 * DIAGONAL))


def inverse_turn(rot_k: int) -> int:
    """The rotation index that turns by minus ``rot_k``'s angle: the query turned by ``rot_k`` against an upright
    tile is the upright query against the tile turned by ``inverse_turn(rot_k)`` (one photo, one extraction)."""
    k = rot_k % 8
    return (4 - k) % 4 if k < DIAGONAL else DIAGONAL + (3 - (k - DIAGONAL)) % 4


def rotation_angle(rot_k: int) -> float:
    """The counter-clockwise turn (degrees) of rotation index ``rot_k``: 0-3 quarter turns, 4-7 diagonals."""
    return 90.0 * (rot_k % 4) + (45.0 if rot_k % 8 >= DIAGONAL else 0.0)


def resize(image: np.ndarray, factor: float, nearest: bool = False, enlarge: str = "linear") -> np.ndarray:
    """``image`` resized by ``factor`` (each side ``round(side * factor)``, at least 1 px); ``image`` itself when
    the factor is 1. Area-averaged when shrinking, nearest-neighbour for masks (``nearest``), ``enlarge``
    ("linear" or "cubic") when enlarging."""
    if abs(factor - 1) < 1e-6:
        return image
    size = (max(1, round(image.shape[1] * factor)), max(1, round(image.shape[0] * factor)))
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA if factor < 1 else _ENLARGE[enlarge]
    return cv2.resize(image, size, interpolation=interp)


def resize_to_side(image: np.ndarray, side: int | None, enlarge: str = "cubic") -> tuple[np.ndarray, float]:
    """(``image`` with its longer side ``side`` px, the factor applied); unchanged (factor 1) for ``side`` None."""
    if not side:
        return image, 1.0
    s = side / max(image.shape[:2])
    if abs(s - 1) < 1e-6:
        return image, 1.0
    return resize(image, s, enlarge=enlarge), s


def fit_within(image: np.ndarray, max_side: float | None) -> np.ndarray:
    """``image`` shrunk so its longer side is at most ``max_side`` px (area-averaged); never enlarged."""
    side = max(image.shape[:2])
    if not max_side or side <= max_side:
        return image
    return resize(image, max_side / side)


def project_points(H: np.ndarray, pts) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) points through the 3x3 homography ``H``: (projected points, their homogeneous w). Points with
    w = 0 come out infinite; callers that need a real view check ``w``."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    v = np.c_[pts, np.ones(len(pts))] @ np.asarray(H, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return v[:, :2] / v[:, 2:3], v[:, 2]


def turned(image: np.ndarray, angle: float, fill: str = "mirror") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``image`` turned ``angle`` degrees (OpenCV, counter-clockwise) on a canvas that holds all of it, the mask of
    its own pixels, and the 2x3 affine from image to canvas (pixel-centre coordinates); the canvas centre is the
    image centre, so the centre's position is unchanged.

    The canvas corners outside the image are ``fill``ed: "mirror" (the image reflected across its edges) or
    "black". Features are extracted with the mask, but the extractor normalises the whole canvas: on low-contrast
    NAIP 2009 crops black corners took a query turned to its true heading from 95-140 inliers to 3-9
    (naip_20090818_r_012: 95 unturned at 14° off, 9 turned with black corners, 140 mirrored)."""
    h, w = image.shape[:2]
    a = math.radians(angle)
    c, s = abs(math.cos(a)), abs(math.sin(a))
    W, H = int(math.ceil(w * c + h * s - 1e-6)), int(math.ceil(w * s + h * c - 1e-6))
    R = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), angle, 1.0)
    R[:, 2] += ((W - w) / 2.0, (H - h) / 2.0)
    border = {"mirror": cv2.BORDER_REFLECT_101, "black": cv2.BORDER_CONSTANT}[fill]
    out = cv2.warpAffine(image, R, (W, H), flags=cv2.INTER_LINEAR, borderMode=border, borderValue=(0, 0, 0))
    mask = cv2.warpAffine(np.full((h, w), 255, np.uint8), R, (W, H), flags=cv2.INTER_NEAREST) > 0
    return out, cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0, R


def unturn_points(xy: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Points (pixel-edge origin) of a :func:`turned` canvas back in the image it was turned from."""
    inv = cv2.invertAffineTransform(np.asarray(affine, np.float64))
    p = np.asarray(xy, np.float64) - 0.5
    return p @ inv[:, :2].T + inv[:, 2] + 0.5
