"""Stages 4-5: from a query image to a fix (lat/lon + status).

``localizer`` (:class:`~aeroloc.localization.localizer.Localizer`: retrieval -> dense stage -> re-ranking
cascade -> alignment), ``dense_stage`` (structural matching of the query over the map), ``cascade`` (re-ranking
by verified inliers), ``window`` (re-matching on the map window a match points at), ``alignment`` (query centre
-> tile -> lat/lon), ``results`` (the typed result and its resumable CSV).

Imports: aeroloc.matching, aeroloc.retrieval, aeroloc.maps, aeroloc.core.
"""
