"""A window of a map cut at a heading with exact geometry: the test input whose true position is known to a
fraction of a pixel (tests of the geometry chain and of photos on black canvases)."""

from __future__ import annotations

import numpy as np


def cut_at_heading(image: np.ndarray, cx: float, cy: float, heading_deg: float, side: int) -> np.ndarray:
    """A ``side`` px square of ``image`` centred on (cx, cy) (pixel-edge coordinates, the georeference's frame),
    its content turned ``heading_deg`` as the sets' crops (aeroloc.flight.composite.crop_to_map), each output
    pixel centre sampled exactly: OpenCV's inverse map takes pixel indices, half a pixel from the edge frame."""
    import cv2

    from aeroloc.flight.composite import crop_to_map, index_frame

    a = index_frame(crop_to_map(heading_deg, 1.0, (cx, cy), (side, side)))
    return cv2.warpAffine(image, a, (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
