"""The query-time pipeline for one image: retrieve top-N -> dense stage or re-rank to top-K by verified inliers
-> align -> lat/lon (:class:`Localizer`). Query sets go through :mod:`aeroloc.localization.run`."""

from __future__ import annotations

import time
import warnings
from functools import cached_property

import numpy as np

from aeroloc.core.canvas import View, photo_view
from aeroloc.core.frames import project_points
from aeroloc.localization.alignment import Alignment, align, reach_m
from aeroloc.localization.options import LocalizeOptions
from aeroloc.localization.results import AMBIGUOUS, Localization
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.retriever import Retriever


class Localizer:
    """One database's query-time pipeline: ``Localizer(db, options)(name, image)`` -> :class:`Localization`.

    Retrieval gives the top-N tiles; the dense stage (when the query's ground resolution is known) places the query
    over the map; otherwise the re-ranking cascade picks the best tile by verified inliers and alignment maps the
    query centre through it to lat/lon."""

    def __init__(self, db: Database, options: LocalizeOptions | None = None, device="cpu"):
        from aeroloc.localization.cascade import Reranker

        self.db = db
        self.options = options = options or LocalizeOptions()
        self.retriever = Retriever(db, options.method, device, options.rotations)
        self.reranker = Reranker(db, options.rerank, device, options.cascade_overrides()) if options.rerank else None
        m = db.info["map"]
        self.map_size = (int(m["width"]), int(m["height"]))
        self.map_gsd = float(m["resolution_m"]) if m.get("resolution_m") else None

    def __call__(self, name: str, image: np.ndarray, top_n: int | None = None, priors=None) -> Localization:
        """Localize one RGB image (HxWx3 uint8) named ``name``; ``top_n`` overrides the options' for this image;
        ``priors`` (aeroloc.core.priors.Priors) what the aircraft knew of this image's ground resolution and
        heading (unknown ones are searched)."""
        from aeroloc.core.device import single_threaded_blas
        from aeroloc.localization.screening import refusal

        if priors is not None:  # a camera's height and lens give a ground resolution only with the image's width
            priors = priors.with_image_width(image.shape[1], name)
        t0 = time.perf_counter()
        view = photo_view(image) if self.options.trim_canvas else None
        view_ms = (time.perf_counter() - t0) * 1000  # ~5 us for a photo on no canvas, tens of ms for one on a canvas
        if view is not None:  # a photo on a black canvas: the photo alone, whose centre is the same point
            image = view.image
            if priors is not None:
                priors = priors.for_view(image.shape[1], view.turn_deg)
        work_side = self.reranker.conf.get("query_side") if self.reranker is not None else None
        why = refusal(image, self.map_gsd, priors, work_side)
        if why is not None:
            return Localization(name, status=why)
        with single_threaded_blas():
            out = self._localize(name, image, top_n or self.options.top_n, self.options.top_k, priors)
            self._refine(image, out)
        if view is not None:
            _in_whole_image(out, view)
        out.times_ms["descriptor"] = out.times_ms.get("descriptor", 0.0) + view_ms  # the query's preparation
        return self._assess(out)

    def _refine(self, image: np.ndarray, out: Localization) -> None:
        """A local-feature fix (the cascade's, or a sweep candidate local features confirmed) moved to the dense
        structure's peak at its own heading and scale when the two agree (aeroloc.localization.structure_refine);
        dense and structure-confirmed fixes are structural already. The time counts as alignment."""
        if not out.localized or not self.options.structure_refine or self.map_gsd is None:
            return
        from aeroloc.localization.structure_refine import placement_of, refine_fix

        if out.dense is None and out.placement is None and out.best is not None and out.best.H is not None:
            angle, scale = placement_of(out.best.H)
        elif out.placement is not None and "structure confirmed" not in out.status:
            angle, scale = out.placement.angle, out.placement.scale
        else:
            return
        if self.dense is None:
            return
        t0 = time.perf_counter()
        r = refine_fix(self.dense, image, out.lat, out.lon, angle, scale)
        out.times_ms["align"] = out.times_ms.get("align", 0.0) + (time.perf_counter() - t0) * 1000
        if r is not None:
            out.lat, out.lon, out.refined_m = r.lat, r.lon, r.moved_m

    def _assess(self, out: Localization) -> Localization:
        """The fix's calibrated confidence and sigma (aeroloc.localization.confidence); a fix below the options'
        confidence floor becomes "not localized"."""
        from aeroloc.localization.confidence import assess

        if not out.localized or self.map_gsd is None:
            return out
        out.confidence, out.sigma_m = assess(out.status, out.inliers, self.map_gsd)
        if out.confidence < self.options.min_confidence:
            out.status = (
                f"not localized: confidence {out.confidence:.2f} < {self.options.min_confidence} ({out.status})"
            )
            out.lat = out.lon = float("nan")
            out.confidence = out.sigma_m = None
        return out

    def dense_search(self, image: np.ndarray, priors=None) -> dict | None:
        """The dense stage's search for this image: its ground resolution (the image's prior, else the options'),
        headings (the prior's range, else the options') and the scales its tolerance asks for; None when the
        ground resolution is unknown."""
        from aeroloc.localization.dense_stage import scale_ladder

        p = priors  # already at the image's width (__call__)
        if p is not None and p.gsd_m is not None:
            gsd, scales = p.gsd_m, scale_ladder(p.gsd_tol)
        elif self.options.query_gsd is not None:
            gsd, scales = self.options.query_gsd, None
        else:
            return None
        angles = p.heading_search() if p is not None else None
        # a query's own prior: its answer is checked by local features (the dense stage's acceptance was fitted
        # on NAIP; on levir-tx it trusted a fix 53 m off at ratio 1.65-1.76); --query-gsd keeps its NAIP rule
        verify = p is not None and p.gsd_m is not None
        return {"query_gsd": gsd, "angles": angles, "scales": scales, "verify": verify}

    def _dense_confirmed(self, image: np.ndarray, d, out: Localization) -> bool:
        """Whether local features agree with the dense answer ``d``: the query, turned by the dense heading
        itself (aeroloc.matching.features.extract's exact turn), matched against the tiles that contain
        the dense position, aligns within max(25 m, 10 map px) of it. Times go into ``out``; no re-ranker means no confirmation.
        Where the two agree on ground the map shows twice, the answer is not confirmed and ``out.status`` says
        "two places match" (the caller then stops: no later stage may pick one of the copies)."""
        if self.reranker is None:
            return False
        from aeroloc.core import geo

        tiles = self._tiles_around(d.col, d.row, [])[:3]
        rr = self.reranker(image, tiles, 1, rotations=[0], turn_deg=float(d.match.angle))
        _add_times(out, rr.times_ms)
        best = rr.candidates[0]
        a = self._align_best(image, best)
        if not a.localized:
            return False
        out.inliers = best.score
        reach = reach_m(self.dense.map_gsd)
        if float(geo.geodesic_distance(d.lat, d.lon, a.lat, a.lon)) > reach:
            return False
        doubt = self._echo_rival(self._footprint(image, best), a)
        if doubt:  # the dense answer and the features agree, on ground the map also shows elsewhere
            out.status = f"not localized: {doubt}"
            return False
        return True

    def _localize(self, name: str, image: np.ndarray, top_n: int, top_k: int, priors=None) -> Localization:
        # the photo's local features, shared by every cascade of this localization (each rotation extracted once)
        query = self.reranker.query_features(image, prior_turn(priors)[1]) if self.reranker is not None else None
        heading = prior_heading(priors)
        unknown = heading is None and not self.options.north_up and self.options.rotations == 1
        r = self.retriever(image, top_n, heading=heading, turned=unknown)
        out = Localization(name, retrieved=r.tile_ids, times_ms=dict(r.times_ms))
        known = priors is not None and priors.known
        if known and self.sweep is not None and self.reranker is not None:
            # a heading or scale prior: the cascade at the turns the heading allows, then the sweep narrowed to it
            self._cascade(image, r.tile_ids, top_k, priors, out, query=query)
            if not out.localized and AMBIGUOUS not in out.status:
                self._turned_retrieval(image, r.tile_ids, top_n, top_k, priors, out, query)
            if not out.localized and AMBIGUOUS not in out.status:
                self._sweep_fix(image, priors, out, r.tile_ids, top_k)
            return out
        dense_ms = 0.0
        search = self.dense_search(image, priors)
        if search is not None and self.dense is not None:
            verify = search.pop("verify")
            t0 = time.perf_counter()
            d = self.dense.locate(image, [self.db.by_id[t] for t in r.tile_ids], **search)
            dense_ms = (time.perf_counter() - t0) * 1000
            if d is not None and (not verify or self._dense_confirmed(image, d, out)):
                out.times_ms["align"] = dense_ms
                status = d.status()
                if verify:
                    status = status[:-1] + f", confirmed by {out.inliers} local-feature inliers)"
                out.lat, out.lon, out.status, out.dense = d.lat, d.lon, status, d
                out.top_tiles = self._tiles_around(d.col, d.row, r.tile_ids)[: top_k or None]
                return out
            out.inliers = 0
            if AMBIGUOUS in out.status:  # two places match: no later stage may pick one of them
                out.times_ms["align"] = dense_ms
                return out
        if self.reranker is None:  # retrieval only: best tile centre, no alignment
            out.top_tiles = r.tile_ids[:top_k] if top_k else r.tile_ids
            out.lat, out.lon = self.db.by_id[r.tile_ids[0]].centre_latlon
            out.status = "retrieval only"
            return out
        self._cascade(image, r.tile_ids, top_k, priors, out, dense_ms, query, r.turn_scores)
        tried = list(r.tile_ids)
        if not out.localized and AMBIGUOUS not in out.status:
            tried += self._turned_retrieval(image, r.tile_ids, top_n, top_k, priors, out, query)
        if not out.localized and AMBIGUOUS not in out.status and not known:
            self._neighbour_fix(image, r.tile_ids, tried, top_k, priors, out, query)
        ambiguous = AMBIGUOUS in out.status  # two places match: no later stage may pick one of them
        if not out.localized and self.sweep is not None and not known and not self.options.north_up and not ambiguous:
            # heading unknown and the quarter turns found nothing: every heading and scale
            self._sweep_fix(image, None, out, r.tile_ids, top_k)
        return out

    def _turned_retrieval(
        self, image, tried: list[str], top_n: int, top_k: int, priors, out: Localization, query=None
    ) -> list[str]:
        """When the cascade found nothing on the upright query's tiles: retrieve again with the query described at
        ``TURNED_RETRIEVAL_VIEWS`` headings, 45° apart (tiles are upright, so a turned photo's own descriptor can
        miss its place), and run the cascade on the tiles not tried yet. The quarter turns are exact; the
        diagonals are turned on a canvas holding the whole query, corners mirrored (a heading prior's view,
        aeroloc.retrieval.retriever.prior_views). Quarter turns alone: on levir-tx/any (12 queries) the true tile
        moved from outside the top 20 to rank 0 for two photos, and from 13-14 to 3-6 for two more. The
        diagonals added (no priors, every query): levir-tx/any 0.875 -> 0.90, szada-hu/any 0.86 -> 0.92 within
        5 m, 0 wrong; the photos they found look 135°, 307° and 314°, where no quarter turn retrieved their
        place. 7 more descriptors (~1 s here) on queries that would otherwise go on to the sweep. Off for
        north-up queries, when retrieval already
        turns the query (``rotations`` > 1) and when a heading prior turned it upright already
        (aeroloc.retrieval.retriever.prior_views)."""
        if self.options.north_up or self.options.rotations > 1 or prior_heading(priors) is not None:
            return []
        r4 = self.retriever(image, top_n, rotations=TURNED_RETRIEVAL_VIEWS, mirror=True)
        _add_times(out, r4.times_ms)
        seen = set(tried)
        new = [t for t in r4.tile_ids if t not in seen]
        if new:
            self._cascade(image, new, top_k, priors, out, query=query)
        return new

    def _neighbour_fix(self, image, retrieved: list[str], tried: list[str], top_k: int, priors, out, query=None):
        """When no retrieved tile placed a query without priors: the cascade on the tiles beside the first
        ``NEIGHBOUR_SEEDS`` retrieved ones that were not tried (aeroloc.localization.neighbours: a photo across a
        tile border whose best tile retrieval missed). Not for queries with a heading or scale prior: the sweep
        narrowed to the prior places those, and the stage before it cost the NAIP flight's re-localizations (seed
        4: after the outage the frame the sweep placed at once was lost for 18 more frames)."""
        if not self.options.neighbours:
            return
        from aeroloc.localization.neighbours import neighbour_candidates

        t0 = time.perf_counter()
        new = neighbour_candidates(self._neighbourhood, self.db.by_id, retrieved[:NEIGHBOUR_SEEDS], set(tried))
        _add_times(out, {"search": (time.perf_counter() - t0) * 1000})
        if new:
            self._cascade(image, new, top_k, priors, out, query=query)

    @cached_property
    def _neighbourhood(self):
        from aeroloc.localization.neighbours import Neighbourhood

        return Neighbourhood(self.db.tiles)

    def _cascade(
        self, image, tile_ids: list[str], top_k: int, priors, out: Localization, extra_ms=0.0, query=None, turns=None
    ):
        """Re-rank the retrieved tiles at the quarter turns the heading allows, align the best one into ``out``;
        ``query``: the photo's features extracted so far (aeroloc.localization.cascade.QueryFeatures); ``turns``:
        the retrieval's per-turn similarities (the order of the screens when the heading is unknown)."""
        rotations, turn = prior_turn(priors, self._diagonals)
        rr = self.reranker(image, tile_ids, top_k, rotations=rotations, turn_deg=turn, query=query, turn_scores=turns)
        _add_times(out, rr.times_ms)
        self._place(image, rr, out, extra_ms)
        if not out.localized and AMBIGUOUS not in out.status:  # weak screens at their own angle, then again
            before = dict(rr.times_ms)
            if self.reranker.weak_screen_turns(rr):
                self._place(image, rr, out)
            _add_times(out, {k: v - before.get(k, 0.0) for k, v in rr.times_ms.items()})

    def _place(self, image, rr, out: Localization, extra_ms: float = 0.0) -> None:
        """Align the re-ranked best candidate into ``out``: doubts (screen vs matcher, a rival, doubled ground),
        then the window re-alignment of a weak best and of the runners-up."""
        out.top_tiles = [c.tile_id for c in rr.candidates]
        best = rr.candidates[0]
        out.best = best
        t0 = time.perf_counter()
        a = self._align_best(image, best)
        doubt = self.reranker.doubt(best) if a.localized else None
        note = ""
        if not doubt and a.localized:
            doubt, best, a, note = self._rival_or_duel(image, best, rr, a)
            if best is not out.best:  # the rival won the duel: it heads the list
                out.best, out.top_tiles = best, [best.tile_id] + [t for t in out.top_tiles if t != best.tile_id]
        doubt = doubt or (self._echo_rival(self._footprint(image, best), a) if a.localized else None)
        if doubt:
            a = Alignment(f"not localized: {doubt}")
        if self._should_realign(a, best, (image.shape[1], image.shape[0])):
            a = self._realign(image, best, rr.query_at(best.rot_k)) or a
            if not a.localized:
                a, best = self._realign_runners_up(image, rr, best, a)
                out.best = best
            # a window's fix faces the doubled-ground check as a tile's does (szada_north_0_01 made 2x coarser
            # than the map, rough priors: its tile's match was weak, the window placed it on the other copy of the
            # forest strip, 551 m off, unchecked; without priors the tile's match was checked and refused)
            echo = self._echo_rival(a.corners, a) if a.localized else None  # no corners kept: None
            if echo:
                a = Alignment(f"not localized: {echo}")
        out.times_ms["align"] = out.times_ms.get("align", 0.0) + (time.perf_counter() - t0) * 1000 + extra_ms
        out.lat, out.lon, out.status, out.inliers = a.lat, a.lon, a.status, best.score
        if a.localized and note:
            out.status = f"{a.status} ({note})"

    def _sweep_fix(self, image: np.ndarray, priors, out: Localization, retrieved: list[str], top_k: int) -> bool:
        """The sweep's candidates confirmed by local features (aeroloc.localization.sweep_stage) into ``out``;
        True also when two far-apart places are confirmed ("not localized": ambiguous); False (``out``
        untouched but for the time spent) when none is confirmed."""
        from aeroloc.localization.sweep_stage import accept_fix

        t0 = time.perf_counter()
        found = accept_fix(self.sweep, self.reranker, image, priors)
        out.times_ms["sweep"] = out.times_ms.get("sweep", 0.0) + (time.perf_counter() - t0) * 1000
        if found is None:
            return False
        fix, why = found
        # a repeated pattern (no fix), or a fix on ground the map shows twice: no other stage may pick a place
        doubt = None if fix is None else self._echo_rival(self._sweep_footprint(image, fix), fix.alignment)
        if fix is None or doubt:
            out.lat = out.lon = float("nan")
            out.status, out.inliers, out.best, out.dense = f"not localized: {doubt or why}", 0, None, None
            return True
        a, h = fix.alignment, fix.hypothesis
        out.lat, out.lon, out.inliers, out.best, out.dense = a.lat, a.lon, fix.inliers, None, None
        out.placement = h
        out.status = f"localized (sweep: heading {h.angle:.0f}°, scale {h.scale:.2f}; {why})"
        col, row = self.map.latlon_to_pixel(a.lat, a.lon)
        out.top_tiles = self._tiles_around(float(col), float(row), retrieved)[: top_k or None]
        return True

    def _sweep_footprint(self, image: np.ndarray, fix) -> np.ndarray:
        """A sweep fix's footprint: the query at the confirmed centre, turned and scaled as its hypothesis says."""
        from aeroloc.localization.window import footprint_at

        a, h = fix.alignment, fix.hypothesis
        col, row = self.map.latlon_to_pixel(a.lat, a.lon)
        return footprint_at(float(col), float(row), h.angle, h.scale, (image.shape[1], image.shape[0]))

    def _rival_or_duel(self, image: np.ndarray, best, rr, a: Alignment):
        """(doubt or None, candidate, alignment, note): ``best`` and ``a`` when no far place rivals it; when one
        does, the two re-matched on equal framing (aeroloc.localization.duel), and the decisive winner taken if
        no third place rivals it (``note`` says so, for the status); otherwise the rival's doubt. One duel at
        most (two window matches)."""
        from aeroloc.localization.duel import Contender, duel

        rival = self._rival(image, best, rr, a)
        if rival is None:
            return None, best, a, ""
        if self.map is None:
            return rival[0], best, a, ""
        conf = self.options.sweep_conf()
        c = rival[1]
        won = duel(
            self.map,
            self.reranker,
            image,
            Contender(best, rr.query_at(best.rot_k)),
            Contender(c, rr.query_at(c.rot_k)),
            conf["rival_margin"],
            conf["confirm_inliers"],
            self.map_size,
        )
        if won is None:
            return rival[0], best, a, ""
        loser = self._place_of(image, c) if won.winner is best else a  # ``a``: the best's own placement
        again = self._rival(image, won.winner, rr, won.alignment, beaten=loser)
        if again:
            return again[0], won.winner, won.alignment, ""
        note = f"a far place also matched: {won.counts[0]} vs {won.counts[1]} inliers on equal map windows"
        return None, won.winner, won.alignment, note

    def _rival(self, image: np.ndarray, best, rr, a: Alignment, beaten: Alignment | None = None):
        """(why ``best`` is ambiguous, the rival candidate), or None: another tile aligns the query at a place
        more than two reaches (max(25 m, 10 map px)) away with at least half the best's inliers (and the sweep's
        inlier floor), i.e. a repeated pattern. On szada-hu farmland two fields 547 m apart screened 24 and 22
        inliers and the cascade took the wrong one (44 verified inliers; the right one 22). A far tile whose
        screen reaches half the best's is verified by the matcher first, unless its screen stays at noise level
        with the query at its own angle (aeroloc.localization.cascade.Reranker.screen_is_noise). Tiles within two
        reaches of ``beaten`` (a place the best won a duel against) are no rivals."""
        reach = reach_m(self.map_gsd)
        # a rival is a place the sweep would confirm on its own (its inlier floor), within its margin of the best
        conf = self.options.sweep_conf()
        floor, margin = conf["confirm_inliers"], conf["rival_margin"]
        verified = False
        score = best.score  # the best's own count, like with like: the matcher's once a rival has the matcher's
        for c in rr.ranked:
            if c is best or c.H is None or (beaten is not None and not self._far(image, c, beaten, reach)):
                continue
            if not verified and c.inliers < 0 and margin * c.screen > best.screen and self._far(image, c, a, reach):
                verified = True  # the strongest such tile only: one more matcher run at most (two: the best's)
                if rr.features is not None and not self.reranker.screen_is_noise(rr.features, c):
                    score = self._matched_score(best, rr) if best.inliers < 0 else score
                    c.take(*self.reranker.match_at(rr.features, c), c.rot_k, "verify")
            strong = c.score >= floor and margin * c.score >= score
            if strong and self._far(image, c, a, reach):
                return f"{AMBIGUOUS} ({score} and {c.score} inliers, more than {2 * reach:.0f} m apart)", c
        return None

    def _footprint(self, image: np.ndarray, best) -> np.ndarray | None:
        """The query's corners in map px through a candidate's transform (None without a usable one)."""
        from aeroloc.localization.window import footprint_in_map

        if best.H is None:
            return None
        return footprint_in_map(best.H, (image.shape[1], image.shape[0]), self.db.by_id[best.tile_id])

    def _echo_rival(self, corners: np.ndarray | None, a: Alignment) -> str | None:
        """Why ``a`` is ambiguous because the map shows its ground twice (aeroloc.retrieval.echoes), or None: the
        map under the query's footprint (its corners through the fix's transform) is compared with the map at
        each echo offset of the tiles holding the fix (best masked correlation within a few pixels); where the two
        are the same pixels (``ECHO_SAME``) nothing the query shows can tell the places apart. Where the footprint
        reaches ground shown once, the copies differ and the fix stands on the query's own evidence. szada-hu/any,
        rough priors: szada_any_0_04 was placed 546 m off, on the other copy of a forest strip (19 and 12-23
        inliers on windows at the two copies: a coin flip)."""
        echoes = self.echoes
        if not echoes or self.map is None or corners is None:
            return None
        col, row = self.map.latlon_to_pixel(a.lat, a.lon)
        offsets: list[tuple[int, int]] = []
        for t in self._tiles_around(float(col), float(row), []):
            for e in echoes.get(t, []):
                if all(abs(e.dx - dx) + abs(e.dy - dy) > 16 for dx, dy in offsets):
                    offsets.append((e.dx, e.dy))
        if not offsets:
            return None
        from aeroloc.retrieval.echoes import same_ground

        for dx, dy in offsets:
            score = same_ground(self.map, corners, dx, dy)
            if score is not None and score >= ECHO_SAME:
                apart = float(np.hypot(dx, dy)) * (self.map_gsd or 1.0)
                return (
                    f"{AMBIGUOUS} (the map shows the query's ground twice, {apart:.0f} m apart: correlation "
                    f"{score:.2f} between the two copies)"
                )
        return None

    @cached_property
    def echoes(self) -> dict[str, list]:
        """The database's echoes by tile id (aeroloc.retrieval.echoes). A database built before the check (or whose
        tiles changed) has none stored: a small one (<= ``ECHO_LAZY_MAX`` tiles, ~12 ms a tile) gets them found and
        written now, a larger one a warning that repeated ground goes unchecked until ``aeroloc build`` runs again."""
        from aeroloc.retrieval.echoes import build_echoes, find_echoes, load_echoes

        found = load_echoes(self.db, self.options.method)
        if found is None and len(self.db.tiles) <= ECHO_LAZY_MAX:
            try:
                found = build_echoes(self.db, self.options.method)
            except OSError:  # a read-only database: found for this run only
                found = find_echoes(self.db, self.options.method)
        elif found is None:
            warnings.warn(
                f"{self.db.folder}: built before the repeated-ground check ({len(self.db.tiles)} tiles); ground the "
                "map shows twice is not checked until 'aeroloc build' runs again",
                stacklevel=2,
            )
        by: dict[str, list] = {}
        for e in found or []:
            by.setdefault(e.tile_id, []).append(e)
        return by

    def _matched_score(self, best, rr) -> int:
        """The matcher's inliers on a best candidate the screen alone accepted (its transform is kept): a rival
        verified by the matcher is compared with the same count. Matcher counts run 1.5-3x screen counts: on
        szada-hu/any a screen-accepted right tile (80 screen, 256 matcher inliers) was refused as ambiguous
        against a repeated forest edge 548 m away (46 screen, 122 matcher)."""
        if rr.features is None:
            return best.score
        return max(best.score, self.reranker.match_at(rr.features, best)[0])

    def _place_of(self, image: np.ndarray, c) -> Alignment:
        """Candidate ``c``'s own placement of the query (whatever its inliers)."""
        return align(c.H, max(c.score, 4), (image.shape[1], image.shape[0]), self.db.by_id[c.tile_id], self.map_size, 4)

    def _far(self, image: np.ndarray, c, a: Alignment, reach: float) -> bool:
        """Whether candidate ``c``'s own alignment puts the query more than two reaches from ``a``."""
        from aeroloc.core import geo

        b = self._place_of(image, c)
        return b.localized and float(geo.geodesic_distance(a.lat, a.lon, b.lat, b.lon)) > 2 * reach

    def _align_best(self, image: np.ndarray, best) -> Alignment:
        """The query centre through the best candidate's transform into its tile, then to lat/lon."""
        size = (image.shape[1], image.shape[0])
        return align(
            best.H, best.score, size, self.db.by_id[best.tile_id], self.map_size, self.reranker.conf["min_inliers"]
        )

    def _should_realign(self, a: Alignment, best, query_size) -> bool:
        from aeroloc.localization.window import beyond_tile

        conf = self.reranker.conf
        if best.H is None:
            return False
        if not a.localized:
            return conf["refine_min"] is not None and conf["refine_min"] <= best.score < conf["min_inliers"]
        return (
            conf["refine_outside"] is not None
            and beyond_tile(best.H, query_size, self.db.by_id[best.tile_id]) > conf["refine_outside"]
        )

    def _realign(self, image: np.ndarray, best, qf) -> Alignment | None:
        """The best match re-matched against the map window its transform says the query covers (aeroloc.localization.window):
        the window's alignment when it passes with more inliers than the tile had (``best`` then takes the
        window's inliers and transform), else None."""
        from aeroloc.localization.window import footprint_in_map, query_window

        tile = self.db.by_id[best.tile_id]
        if qf is None or self.map is None:
            return None
        window = query_window(self.map, tile, best.H, (image.shape[1], image.shape[0]))
        if window is None:
            return None
        n, H, n_matches, _vis = self.reranker.match_window(qf, window, tile)
        size = (image.shape[1], image.shape[0])
        a = align(H, n, size, window.tile, self.map_size, self.reranker.conf["min_inliers"])
        if not a.localized or n <= best.score:
            return None
        best.inliers, best.H, best.n_matches, best.matches = n, H, n_matches, None
        a.corners = footprint_in_map(H, size, window.tile)
        return a

    def _realign_runners_up(self, image: np.ndarray, rr, best, a: Alignment):
        """When the best candidate's window re-match fails: the next candidates the matcher verified with
        ``refine_min`` inliers or more (up to ``refine_runners_up`` of them, best first), each re-matched against its
        own window; the first that passes, and is not rivalled by a far place (:meth:`_rival`), replaces the best.
        levir_any_2_04 (no heading prior): its one retrieved true tile, 17° off its turn, had 9 verified inliers
        and its window 79; a wrong tile had 18, its window too few. Returns (alignment, candidate)."""
        n = self.reranker.conf.get("refine_runners_up", 0)
        floor = self.reranker.conf["refine_min"]
        others = [c for c in rr.ranked if c is not best and c.H is not None and c.inliers >= floor][:n]
        for c in others:
            found = self._realign(image, c, rr.query_at(c.rot_k))
            if found is None:
                continue
            rival = self._rival(image, c, rr, found)
            return (Alignment(f"not localized: {rival[0]}"), c) if rival else (found, c)
        return a, best

    def _tiles_around(self, col: float, row: float, retrieved: list[str]) -> list[str]:
        """The re-ranked list for a dense position: every tile containing it (nearest centre first, retrieved or
        not), then the other retrieved tiles in retrieval order."""
        ids = [t.id for t in self._neighbourhood.containing(col, row)]
        taken = set(ids)
        return ids + [t for t in retrieved if t not in taken]

    @property
    def _diagonals(self) -> bool:
        """Whether the re-ranker turns queries by 45° too (its conf's ``diagonals``), so turns are 45° apart."""
        return bool(self.reranker is not None and self.reranker.conf.get("diagonals"))

    @cached_property
    def dense(self):
        """The dense structural stage (aeroloc.localization.dense_stage) when the queries' ground resolution is known, else None;
        also None (with a warning) when the map can't be opened."""
        from aeroloc.localization.dense_stage import DenseMapLocator

        if self.map is None:
            return None
        return DenseMapLocator(self.map, conf=self.options.dense_conf())

    @cached_property
    def sweep(self):
        """The any-heading, any-scale sweep over the whole map (aeroloc.localization.sweep_stage), or None: off in
        the options, no re-ranker to confirm with, no map, or a map too large to sweep whole."""
        from aeroloc.localization.sweep_stage import open_sweep

        if not self.options.sweep or self.reranker is None:
            return None
        return open_sweep(self.map, self.options.sweep_overrides)

    @cached_property
    def map(self):
        """The database's map, opened on first use; None (with a warning) when it can't be opened any more."""
        from aeroloc.localization.window import open_map_for_refine

        return open_map_for_refine(self.db.info["map"]["path"])


def prior_rotations(priors, diagonals: bool = True) -> list[int] | None:
    """The rotations (aeroloc.matching.features.rotation_angle's indices, as the re-ranker uses them) worth
    trying for a heading prior: every turn that some heading within the tolerance lies within half a step of
    (22.5° with the diagonals, 45° with quarter turns only), nearest first; None (the re-ranker's own) when
    the heading is unknown or so uncertain that every turn qualifies. So the true heading is never more than
    half a step off a turn tried: with quarter turns only a heading near a diagonal (45° ± 15°) left 30-45° of
    residual turn, where the matchers break. Checked on NAIP dev-rotated: a query heading h matches at the
    turn nearest h (h = 246°: 122 screen inliers at 270°, <= 9 at 0°, 90°, 180°)."""
    if priors is None or priors.heading_deg is None:
        return None
    from aeroloc.matching.features import DIAGONAL, turns_within

    half_step = 22.5 if diagonals else 45.0
    ks = turns_within(priors.heading_deg, half_step + priors.heading_tol_deg, diagonals)
    return ks if len(ks) < (2 if diagonals else 1) * DIAGONAL else None


TURNED_RETRIEVAL_VIEWS = 8  # headings the turned retrieval describes a query at (45° apart, see _turned_retrieval)
NEIGHBOUR_SEEDS = 3  # retrieved tiles whose neighbours are re-ranked when nothing else placed a query (_neighbour_fix)
ECHO_LAZY_MAX = 5000  # tiles whose echoes a localizer finds itself when the database has none stored (~1 min)
ECHO_SAME = 0.9  # map correlation of two copies under a footprint that makes them one ground (echoes: 0.98-1.0)
EXACT_TURN_TOL_DEG = 30.0  # a heading known this well is matched at its own angle (the matchers bridge ~35-45°)


def prior_heading(priors) -> tuple[float, float] | None:
    """(heading, tolerance) of a heading prior for retrieval's upright views (aeroloc.retrieval.retriever.prior_views),
    None when the heading is unknown or its tolerance spans the circle."""
    return None if priors is None else priors.heading


def prior_turn(priors, diagonals: bool = True) -> tuple[list[int] | None, float]:
    """(rotations, exact turn in OpenCV degrees) for the re-ranker: a heading known within
    ``EXACT_TURN_TOL_DEG`` turns the query by the heading itself (mirrored canvas, aeroloc.matching.features.extract)
    and tries that view alone; otherwise the discrete turns of :func:`prior_rotations`. The exact turn leaves
    only the sensor's error: on levir-tx/any with rough priors (±15°) the true tiles' screen inliers rose from
    486 to 709 in all (12 queries) and the matcher's from 1599 to 2090; nearest-turn views were up to 37.5° off."""
    if priors is not None and priors.heading_deg is not None and priors.heading_tol_deg <= EXACT_TURN_TOL_DEG:
        return [0], float(priors.heading_deg)
    return prior_rotations(priors, diagonals), 0.0


def _add_times(out: Localization, times_ms: dict) -> None:
    """Stage times added to the result's (a confirmation and the cascade after it both count)."""
    for stage, ms in times_ms.items():
        out.times_ms[stage] = out.times_ms.get(stage, 0.0) + ms


def _in_whole_image(out: Localization, view: View) -> None:
    """A result found on a photo's view (aeroloc.core.canvas), told in the whole image it was made from: the best
    candidate's homography and match points (a flight's pose reads the homography at the frame's centre), and the
    dense and sweep placements' turn. Their centre is the view's, which is the whole image's."""
    from dataclasses import replace

    best = out.best
    if best is not None and best.H is not None:
        best.H = best.H @ view.to_view
    if best is not None and best.matches is not None:
        q, t, inl = best.matches
        best.matches = (project_points(np.linalg.inv(view.to_view), q)[0], t, inl)
    if view.turn_deg:
        if out.dense is not None:
            out.dense.match.angle = out.dense.match.angle + view.turn_deg
        if out.placement is not None:
            out.placement = replace(out.placement, angle=out.placement.angle + view.turn_deg)
