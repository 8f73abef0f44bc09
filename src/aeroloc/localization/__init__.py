"""Stages 4-5: from a query image to a fix (lat/lon + status).

``options`` (:class:`~aeroloc.localization.options.LocalizeOptions`: every setting, validated once),
``localizer`` (:class:`~aeroloc.localization.localizer.Localizer`: retrieval -> dense stage -> re-ranking cascade
-> alignment, for one image), ``run`` (a query set into a resumable results CSV), ``results`` (the one result
type, :class:`~aeroloc.localization.results.Localization`, and its CSV row), ``dense_stage`` (structural matching
of the query over the map), ``cascade`` (re-ranking by verified inliers), ``window`` (re-matching on the map window
a match points at), ``alignment`` (query centre -> tile -> lat/lon), ``visualize`` (match pictures), ``build``
(everything a Localizer needs, in one call).

Imports: aeroloc.matching, aeroloc.retrieval, aeroloc.maps, aeroloc.core.
"""
