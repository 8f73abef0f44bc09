"""A photo that arrives on a black canvas (letterboxed, padded, or turned with black corners) seen as the photo
alone: turned back upright when its edges are tilted, then cut to its centred window of imagery.

The local-feature networks normalise their whole input (XFeat's first layer is an instance norm), so a black
canvas skews every descriptor of the imagery: 20 NAIP photos of 2009-2010 were placed 18 times as they are, 7
times centred on a black canvas 1.5x their side, 8 times turned on a black-cornered canvas
(``benchmarks/black_canvas.py``). Masking the black is not enough; filling it was tried and hurt frames whose
missing ground is black. Turning and cutting change nothing the photo shows: the turn is about the image's centre
and the window is centred on it, so the point a fix places is the same point, and an image whose corners are not
all canvas is left as it is (a frame with ground missing on one side, every photo of the shared sets).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DARK = 12  # a canvas pixel's brightest channel at most this (JPEG leaves black a few levels above 0)
MIN_SIDE = 32  # a window narrower than this is no photo: the image is left as it is (and refused downstream)
RECTANGLE_FILL = 0.95  # the photo fills this share of its tightest turned rectangle: a photo turned on a canvas
# (a JPEG's ringing along a turned edge left one 256 px photo at 0.966 of it; every clean turn fills > 0.99)
MIN_TILT_DEG = 0.5  # edges tilted less than this are upright


@dataclass(frozen=True)
class Window:
    """The photo's window in the image: columns ``[x0, width - x0)``, rows ``[y0, height - y0)``."""

    x0: int
    y0: int
    width: int
    height: int

    def cut(self, image: np.ndarray) -> np.ndarray:
        return image[self.y0 : self.height - self.y0, self.x0 : self.width - self.x0]


@dataclass(frozen=True)
class View:
    """The photo alone: ``image``, made from the whole image by turning it ``turn_deg`` (OpenCV, counter-clockwise)
    about its centre and cutting the centred ``window``; ``to_view`` maps whole-image pixels to view pixels (3x3,
    pixel-edge origin), and the whole image's centre is the view's."""

    image: np.ndarray
    turn_deg: float
    window: Window
    to_view: np.ndarray


def canvas_mask(image: np.ndarray) -> np.ndarray | None:
    """The canvas: dark pixels connected to a corner, when all four corners are dark; None when they are not (the
    image does not sit on a canvas). Dark pixels inside the photo (shadow, deep water) are not canvas unless they
    touch it."""
    h, w = image.shape[:2]
    corners = [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1)]
    if any(np.max(image[r, c]) > DARK for r, c in corners):  # the usual photo: four pixels read, nothing more
        return None
    rgb = image if image.ndim == 2 else image.max(axis=2)
    dark = (rgb <= DARK).astype(np.uint8)
    _, labels = cv2.connectedComponents(dark, connectivity=4)
    corner_labels = {int(labels[r, c]) for r, c in corners}
    return np.isin(labels, list(corner_labels))


def centred_window(canvas: np.ndarray) -> Window | None:
    """The largest window centred on the image's centre that holds no ``canvas`` pixel, or None when it would be
    under :data:`MIN_SIDE` px."""
    h, w = canvas.shape
    ys, xs = np.nonzero(canvas)
    # a canvas pixel lies outside window (x0, y0) when its column depth < x0 or its row depth < y0
    col_depth = np.minimum(xs, w - 1 - xs)
    row_depth = np.minimum(ys, h - 1 - ys)
    deepest = np.full((w + 1) // 2 + 1, -1, np.int64)
    np.maximum.at(deepest, col_depth, row_depth)
    # for margin x0 the window must skip every row depth of canvas pixels at column depth >= x0
    need = np.maximum.accumulate(deepest[::-1])[::-1] + 1
    x0 = np.arange(len(need))
    widths, heights = w - 2 * x0, h - 2 * need
    area = np.where((widths >= MIN_SIDE) & (heights >= MIN_SIDE), widths * heights, -1)
    best = int(np.argmax(area))
    if area[best] <= 0:
        return None
    return Window(best, int(need[best]), w, h)


def tilt(photo: np.ndarray) -> float:
    """Degrees (OpenCV, counter-clockwise, within ±45) that turn a photo region (bool mask) whose edges are tilted
    upright; 0 when it is upright already or not a rectangle (its largest region fills less than
    :data:`RECTANGLE_FILL` of its tightest rectangle)."""
    kernel = np.ones((5, 5), np.uint8)  # the opening drops a JPEG's ringing specks along the edges
    region = cv2.morphologyEx(photo.astype(np.uint8), cv2.MORPH_OPEN, kernel)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return 0.0
    c = max(contours, key=cv2.contourArea)
    (_, _), (rw, rh), angle = cv2.minAreaRect(c)
    if rw * rh <= 0 or cv2.contourArea(c) < RECTANGLE_FILL * rw * rh:
        return 0.0
    t = (angle + 45.0) % 90.0 - 45.0  # the rectangle's edges are tilted t (mod 90) in the image
    return 0.0 if abs(t) < MIN_TILT_DEG else float(t)


def photo_view(image: np.ndarray) -> View | None:
    """The photo alone (:class:`View`), or None when ``image`` does not sit on a canvas (all four corners dark)
    or no window of :data:`MIN_SIDE` px holds the photo."""
    canvas = canvas_mask(image)
    if canvas is None:
        return None
    h, w = canvas.shape
    turn = tilt(~canvas)
    A = np.eye(3)
    if turn:
        # pixel-centre frame for OpenCV's warp; the same turn about (w/2, h/2) in the pixel-edge frame of `to_view`
        R = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), turn, 1.0)
        image = cv2.warpAffine(image, R, (w, h), flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0))
        photo = cv2.warpAffine((~canvas).astype(np.uint8), R, (w, h), flags=cv2.INTER_NEAREST) > 0
        canvas = ~cv2.erode(photo.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)  # no blended edge
        A[:2] = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), turn, 1.0)
    window = centred_window(canvas)
    if window is None:
        return None
    shift = np.array([[1.0, 0.0, -window.x0], [0.0, 1.0, -window.y0], [0.0, 0.0, 1.0]])
    return View(window.cut(image), turn, window, shift @ A)
