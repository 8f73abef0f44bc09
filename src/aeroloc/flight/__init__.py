"""Flight mode: a whole flight localized frame after frame (issue #14).

Sits between ``bench`` and ``localization``: it uses the single-image stages (``Localizer``, the dense stage)
for absolute fixes around a predicted position and adds the filter, the frame-to-frame odometry, the flight
readers and the outputs (GeoJSON, KML, HTML, MAVLink)."""
