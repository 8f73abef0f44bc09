"""A screen accepted without the matcher when another tile sees the same place and no far place comes close.

Tiles overlap (by half a tile in the shared databases), so a query's ground lies in two or more of them. A true
place is therefore screened strongly on each tile that covers it, at one placement; a chance alignment on a wrong
tile rarely repeats on its neighbour at the same place. Over every photo of the seven shared sets, no priors and
rough priors (738 localizations; ``benchmarks/screen_agreement.py``), the best screen of the first cascade was
20-39 inliers on 125; the 6 that placed the query more than a reach off (5 photos) had support 0, 0, 0, 0, 0 and
13 (support: the best screen of another tile placing the query within a reach of it), and the rule below accepts
46, every one within a reach of the truth. So a best screen of at least ``accept_agreed`` inliers (and
``min_inliers``, what a fix needs to align) whose place another tile screens with ``min_screen`` (the count that
settles a heading), and that holds ``agreed_margin`` times the best screen of any place more than two reaches
away (the rival margin: no far place could rival it), is accepted as it is, like a screen of ``accept_screen``.
The matcher's ~0.2-0.4 s is saved on the median photos of NAIP dev-rotated with rough priors (best screens
33-39, neighbours 30-33).
"""

from __future__ import annotations

import math

from aeroloc.localization.alignment import project, reach_m


def centre_px(db, c, query_size: tuple[int, int]) -> tuple[float, float] | None:
    """The query's centre in map px through candidate ``c``'s transform (None without a usable one)."""
    if c.H is None:
        return None
    p = project(c.H, query_size[0] / 2.0, query_size[1] / 2.0)
    if p is None or not all(map(math.isfinite, p)):
        return None
    tile = db.by_id[c.tile_id]
    return tile.col + p[0], tile.row + p[1]


def support_and_far(db, screened: list, query_size: tuple[int, int]) -> tuple[int, int] | None:
    """(support, far): the best screen among ``screened[1:]`` placing the query within a reach (max(25 m, 10 map
    px)) of where ``screened[0]`` places it, and the best placing it more than two reaches away (0 when none);
    None when ``screened[0]`` places it nowhere usable."""
    p0 = centre_px(db, screened[0], query_size)
    if p0 is None:
        return None
    gsd = db.info["map"].get("resolution_m")
    reach = reach_m(float(gsd)) / float(gsd) if gsd else 10.0  # map px
    support = far = 0
    for c in screened[1:]:
        p = centre_px(db, c, query_size)
        if p is None:
            continue
        d = math.hypot(p[0] - p0[0], p[1] - p0[1])
        if d <= reach:
            support = max(support, c.screen)
        elif d > 2 * reach:
            far = max(far, c.screen)
    return support, far


def screen_agreed(db, screened: list, query_size: tuple[int, int], conf: dict) -> bool:
    """Whether the best of ``screened`` (best screen first) is accepted by agreement (module docstring)."""
    if conf.get("accept_agreed") is None or not screened:
        return False
    if screened[0].screen < max(conf["accept_agreed"], conf["min_inliers"]):  # and what a fix needs to align
        return False
    found = support_and_far(db, screened, query_size)
    if found is None:
        return False
    support, far = found
    return support >= conf["min_screen"] and screened[0].screen >= conf["agreed_margin"] * far
