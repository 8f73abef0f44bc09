"""Outputs people open: GeoJSON (a LineString + one Point per frame with its status and sigma), KML (simplekml)
and a MAVLink ``GPS_INPUT`` stream (pymavlink), the message ArduPilot and PX4 take as an external position."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass

from aeroloc.core.io import atomic_write_text

GPS_EPOCH_UNIX = 315964800  # 1980-01-06T00:00:00Z
GPS_LEAP_SECONDS = 18  # GPS - UTC since 2017-01-01


def geojson(points, truth: dict | None = None) -> dict:
    """A FeatureCollection: the estimated track as one LineString (localized points in time order), then one
    Point per localized frame (name, time, status, source, sigma_m, and the truth error when known)."""
    located = [p for p in points if p.localized]
    feats = [
        {
            "type": "Feature",
            "geometry": {"type": "LineString", "coordinates": [[p.lon, p.lat] for p in located]},
            "properties": {"kind": "track", "frames": len(points), "localized": len(located)},
        }
    ]
    for p in located:
        props = {
            "kind": "frame",
            "name": p.name,
            "time": p.time,
            "status": p.status,
            "source": p.source,
            "sigma_m": round(p.sigma_m, 2),
        }
        if truth and p.name in truth:
            props["error_m"] = round(truth_error(p, truth[p.name]), 2)
        feats.append(
            {"type": "Feature", "geometry": {"type": "Point", "coordinates": [p.lon, p.lat]}, "properties": props}
        )
    return {"type": "FeatureCollection", "features": feats}


def truth_error(p, latlon) -> float:
    from aeroloc.core import geo

    return float(geo.geodesic_distance(p.lat, p.lon, latlon[0], latlon[1]))


def write_geojson(path, points, truth=None) -> None:
    atomic_write_text(path, json.dumps(geojson(points, truth)))


def write_kml(path, points) -> None:
    """The track as a KML LineString and a placemark per localized frame (description: status, source, sigma)."""
    import simplekml

    from aeroloc.core.io import atomic_path

    kml = simplekml.Kml(name="aeroloc track")
    located = [p for p in points if p.localized]
    line = kml.newlinestring(name="track", coords=[(p.lon, p.lat) for p in located])
    line.style.linestyle.width = 3
    line.style.linestyle.color = simplekml.Color.red
    folder = kml.newfolder(name="frames")
    for p in located:
        pt = folder.newpoint(name=p.name, coords=[(p.lon, p.lat)])
        pt.description = f"time {p.time:.3f} s; {p.source}; sigma {p.sigma_m:.1f} m; {p.status}"
    with atomic_path(path) as tmp:
        kml.save(str(tmp))


@dataclass(frozen=True)
class GpsTime:
    week: int
    week_ms: int
    unix_usec: int


def gps_time(unix_s: float) -> GpsTime:
    """GPS week and milliseconds into the week of a UTC instant (GPS runs ``GPS_LEAP_SECONDS`` ahead)."""
    g = unix_s - GPS_EPOCH_UNIX + GPS_LEAP_SECONDS
    week = int(g // 604800)
    return GpsTime(week, int(round((g - week * 604800) * 1000)), int(round(unix_s * 1e6)))


class MavlinkOutput:
    """Each track point as one ``GPS_INPUT`` on a pymavlink connection (``udpout:HOST:PORT``, a serial port…).

    Filled: time (the frame's own UTC time when its clock is absolute, else the time of sending), GPS week and
    milliseconds, fix 3D when localized else none, lat/lon in 1e-7 degrees, ``horiz_accuracy`` = sigma (m),
    ``hdop`` = sigma / 5 m (a 5 m user range error), ``satellites_visible`` 10 when localized (autopilots refuse
    fixes with few satellites; there are none here, the number stands for a healthy fix), ``yaw`` from the
    frame's top bearing (centidegrees, 36000 = north, 0 = unknown) where the dialect has the field. Ignored (flags): altitude, vdop, velocities,
    speed and vertical accuracy, which a map fix does not give."""

    def __init__(self, url: str, gps_id: int = 0, source_system: int = 1, source_component: int = 220):
        from pymavlink import mavutil

        self.mav = mavutil.mavlink
        self.conn = mavutil.mavlink_connection(url, source_system=source_system, source_component=source_component)
        self.gps_id = gps_id
        f = self.mav
        self.ignore = (
            f.GPS_INPUT_IGNORE_FLAG_ALT
            | f.GPS_INPUT_IGNORE_FLAG_VDOP
            | f.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ
            | f.GPS_INPUT_IGNORE_FLAG_VEL_VERT
            | f.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY
            | f.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY
        )

    def message(self, p):
        """The GPS_INPUT for one track point."""
        unix = p.time if p.time > 1e9 else time.time()  # an absolute clock (ISO, EXIF) is kept
        g = gps_time(unix)
        ok = p.localized
        sigma = p.sigma_m if ok and math.isfinite(p.sigma_m) else 9999.0
        yaw = 0 if not math.isfinite(p.yaw_deg) else int(round(p.yaw_deg * 100)) % 36000 or 36000
        args = [
            g.unix_usec,
            self.gps_id,
            self.ignore,
            g.week_ms,
            g.week,
            3 if ok else 0,
            int(round(p.lat * 1e7)) if ok else 0,
            int(round(p.lon * 1e7)) if ok else 0,
            0.0,
            float(min(sigma / 5.0, 99.0)),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            float(sigma),
            0.0,
            10 if ok else 0,
        ]
        cls = self.mav.MAVLink_gps_input_message
        if "yaw" in cls.fieldnames:  # a MAVLink 2 extension; older dialects lack it
            args.append(yaw)
        return cls(*args)

    def send(self, p) -> None:
        self.conn.mav.send(self.message(p))

    def close(self) -> None:
        self.conn.close()
