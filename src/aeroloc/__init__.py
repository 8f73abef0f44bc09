"""aeroloc: GNSS-free localization of aerial images against georeferenced maps.

Coordinates in the public API are always ``(lat, lon)`` in WGS84 degrees; readers of formats that put the
longitude first convert at the border.
"""

from aeroloc.core.errors import AerolocError

__version__ = "0.1.0"
__all__ = ["AerolocError", "__version__"]
