"""Sun position from UTC time and site (NOAA/Meeus low-precision series), own implementation.

Internal convention: compass azimuth (0 = north, clockwise, degrees) and geometric elevation.
`to_paint_azimuth` converts to PAINT's (0 = south, positive toward east).
"""

from __future__ import annotations

import numpy as np


def julian_day(unix_seconds) -> np.ndarray:
    return np.asarray(unix_seconds, dtype=float) / 86400.0 + 2440587.5


def sun_compass(unix_seconds, lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]:
    """Return (compass azimuth deg, geometric elevation deg) of the sun centre, without refraction."""
    jd = julian_day(unix_seconds)
    t = (jd - 2451545.0) / 36525.0
    mean_long = np.mod(280.46646 + t * (36000.76983 + t * 0.0003032), 360.0)
    anomaly = np.radians(357.52911 + t * (35999.05029 - 0.0001537 * t))
    ecc = 0.016708634 - t * (0.000042037 + 0.0000001267 * t)
    centre = (
        np.sin(anomaly) * (1.914602 - t * (0.004817 + 0.000014 * t))
        + np.sin(2 * anomaly) * (0.019993 - 0.000101 * t)
        + np.sin(3 * anomaly) * 0.000289
    )
    omega = np.radians(125.04 - 1934.136 * t)
    app_long = np.radians(mean_long + centre - 0.00569 - 0.00478 * np.sin(omega))
    eps0 = 23.0 + (26.0 + (21.448 - t * (46.815 + t * (0.00059 - t * 0.001813))) / 60.0) / 60.0
    eps = np.radians(eps0 + 0.00256 * np.cos(omega))
    decl = np.arcsin(np.sin(eps) * np.sin(app_long))
    y = np.tan(eps / 2.0) ** 2
    l0 = np.radians(mean_long)
    eot_min = 4.0 * np.degrees(
        y * np.sin(2 * l0)
        - 2 * ecc * np.sin(anomaly)
        + 4 * ecc * y * np.sin(anomaly) * np.cos(2 * l0)
        - 0.5 * y * y * np.sin(4 * l0)
        - 1.25 * ecc * ecc * np.sin(2 * anomaly)
    )
    minutes_utc = np.mod(np.asarray(unix_seconds, dtype=float), 86400.0) / 60.0
    solar_min = minutes_utc + eot_min + 4.0 * np.asarray(lon_deg, dtype=float)
    hour_angle = np.radians(solar_min / 4.0 - 180.0)
    lat = np.radians(lat_deg)
    sin_el = np.sin(lat) * np.sin(decl) + np.cos(lat) * np.cos(decl) * np.cos(hour_angle)
    el = np.arcsin(np.clip(sin_el, -1.0, 1.0))
    az = np.arctan2(np.sin(hour_angle), np.cos(hour_angle) * np.sin(lat) - np.tan(decl) * np.cos(lat)) + np.pi
    return np.mod(np.degrees(az), 360.0), np.degrees(el)


def refraction_deg(elevation_deg) -> np.ndarray:
    """Standard-atmosphere refraction (Saemundsson), apparent minus geometric elevation, degrees."""
    h = np.asarray(elevation_deg, dtype=float)
    return 1.02 / np.tan(np.radians(h + 10.3 / (h + 5.11))) / 60.0


def to_paint_azimuth(compass_deg) -> np.ndarray:
    """Compass azimuth (0 north, clockwise) -> PAINT azimuth (0 south, positive east), in (-180, 180]."""
    a = 180.0 - np.asarray(compass_deg, dtype=float)
    return (a + 180.0) % 360.0 - 180.0


def sun_vector_enu(compass_deg, elevation_deg) -> np.ndarray:
    """Unit vector toward the sun in ENU, shape (..., 3)."""
    a, e = np.radians(compass_deg), np.radians(elevation_deg)
    return np.stack([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)], axis=-1)
