"""Two far-apart places both match the query: compare them like with like before calling it ambiguous.

A tile is a retrieval unit, not the query's footprint, so two tiles' inlier counts measure how much of each tile
the query shares as much as which place it shows. szada-hu's map shows one forest strip twice, 547 m apart; a
query on the edge of that strip matched the wrong copy's tile with 115 inliers and its true tile with 55
(szada_any_0_05), and a query off the strip 276 / 146 on its true tile and on the copy (szada_north_1_01). So the
two places are each re-matched on the map window their own transform says the query covers (the same framing
for both, :func:`aeroloc.localization.window.query_window`), and one wins only when its window holds
``margin`` times the other's inliers and at least the sweep's confirmation floor (windows without the query's
ground: mostly <= 15 inliers): the same rule that makes a far place a rival, applied to fair counts. Over the
shared sets' rival refusals the windows gave 31 / 11, 72 / 23, 27 / 10 (true / copy: settled), and 35 / 31,
61 / 93, 45 / 48 (a footprint inside the doubled strip: still refused).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aeroloc.localization.alignment import Alignment, align


@dataclass
class Contender:
    """One place in a duel: its candidate (tile id, transform ``H``, score) and the query features it was matched
    with (at its rotation)."""

    candidate: object
    features: dict | None


@dataclass
class DuelResult:
    winner: object  # the winning candidate
    alignment: Alignment  # its placement (its window's when that passes the inlier threshold, else its tile's)
    counts: tuple[int, int]  # window inliers: winner's, loser's


def window_inliers(map_, reranker, image: np.ndarray, c: Contender):
    """(inliers, transform, window tile) of the query matched on the map window ``c``'s transform points at;
    None when there is no usable window."""
    from aeroloc.localization.window import query_window

    if c.features is None or c.candidate.H is None:
        return None
    tile = reranker.db.by_id[c.candidate.tile_id]
    window = query_window(map_, tile, c.candidate.H, (image.shape[1], image.shape[0]))
    if window is None:
        return None
    n, H, _n_matches, _vis = reranker.match_window(c.features, window, tile)
    return n, H, window.tile


def duel(
    map_, reranker, image: np.ndarray, a: Contender, b: Contender, margin: float, floor: int, map_size
) -> DuelResult | None:
    """The decisive winner of places ``a`` and ``b`` on equal framing (module docstring), or None (no window,
    or neither holds ``margin`` times the other's inliers and ``floor``)."""
    wa, wb = window_inliers(map_, reranker, image, a), window_inliers(map_, reranker, image, b)
    if wa is None or wb is None:
        return None
    for (win, w), (_lose, lw) in (((a, wa), (b, wb)), ((b, wb), (a, wa))):
        n, H, wtile = w
        if n < floor or n <= margin * lw[0]:
            continue
        size = (image.shape[1], image.shape[0])
        placed = align(H, n, size, wtile, map_size, reranker.conf["min_inliers"])
        if not placed.localized:  # the window is framed fairly but holds fewer than a fix needs: its tile places it
            c = win.candidate
            placed = align(c.H, c.score, size, reranker.db.by_id[c.tile_id], map_size, reranker.conf["min_inliers"])
        return DuelResult(win.candidate, placed, (n, lw[0])) if placed.localized else None
    return None
