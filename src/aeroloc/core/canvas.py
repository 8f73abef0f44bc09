"""A photo that arrives on a black canvas (letterboxed, padded, or turned with black corners) cut to its centred
window of imagery.

The local-feature networks normalise their whole input (XFeat's first layer is an instance norm), so a black
canvas skews every descriptor of the imagery: 20 NAIP photos of 2009-2010 were placed 18 times as they are, 7
times centred on a black canvas 1.5x their side, 8 times turned on a black-cornered canvas
(``benchmarks/black_canvas.py``). Masking the black is not enough; filling it was tried and hurt frames whose
missing ground is black. Cutting it away changes nothing the photo shows: the window is centred on the photo's
centre, so the point a fix places is the same point, and an image whose corners are not all canvas is left as it
is (a frame with ground missing on one side, every photo of the shared sets).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DARK = 12  # a canvas pixel's brightest channel at most this (JPEG leaves black a few levels above 0)
MIN_SIDE = 32  # a window narrower than this is no photo: the image is left as it is (and refused downstream)


@dataclass(frozen=True)
class Window:
    """The photo's window in the image: columns ``[x0, width - x0)``, rows ``[y0, height - y0)``."""

    x0: int
    y0: int
    width: int
    height: int

    def cut(self, image: np.ndarray) -> np.ndarray:
        return image[self.y0 : self.height - self.y0, self.x0 : self.width - self.x0]

    def to_image(self) -> np.ndarray:
        """The 3x3 map from window pixels to image pixels (a shift; the same in pixel-edge and pixel-centre
        coordinates)."""
        return np.array([[1.0, 0.0, self.x0], [0.0, 1.0, self.y0], [0.0, 0.0, 1.0]])


def canvas_mask(image: np.ndarray) -> np.ndarray | None:
    """The canvas: dark pixels connected to a corner, when all four corners are dark; None when they are not (the
    image does not sit on a canvas). Dark pixels inside the photo (shadow, deep water) are not canvas unless they
    touch it."""
    rgb = image if image.ndim == 2 else image.max(axis=2)
    h, w = rgb.shape[:2]
    corners = [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1)]
    if any(rgb[r, c] > DARK for r, c in corners):
        return None
    dark = (rgb <= DARK).astype(np.uint8)
    _, labels = cv2.connectedComponents(dark, connectivity=4)
    corner_labels = {int(labels[r, c]) for r, c in corners}
    return np.isin(labels, list(corner_labels))


def photo_window(image: np.ndarray) -> Window | None:
    """The largest window centred on the image's centre that holds no canvas, or None when the image does not
    sit on a canvas or the window would be under :data:`MIN_SIDE` px."""
    canvas = canvas_mask(image)
    if canvas is None:
        return None
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
