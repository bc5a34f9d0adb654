"""WGS84 geodetic <-> ECEF <-> local east-north-up (metres), written from the WGS84 definition."""

from __future__ import annotations

import numpy as np

_A = 6378137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)


def geodetic_to_ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """Geodetic (deg, deg, m) -> ECEF (m), shape (..., 3)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    x = (n + alt_m) * np.cos(lat) * np.cos(lon)
    y = (n + alt_m) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - _E2) + alt_m) * np.sin(lat)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(xyz: np.ndarray) -> np.ndarray:
    """ECEF (m), shape (..., 3) -> geodetic [lat deg, lon deg, alt m] (fixed-point iteration, < 1e-9 m)."""
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - _E2))
    for _ in range(8):
        n = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
        alt = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - _E2 * n / (n + alt)))
    n = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    alt = p / np.cos(lat) - n
    return np.stack([np.degrees(lat), np.degrees(lon), alt], axis=-1)


class LocalFrame:
    """East-north-up frame tangent to the WGS84 ellipsoid at an origin (lat, lon, alt)."""

    def __init__(self, origin_lla) -> None:
        lat0, lon0, alt0 = (float(v) for v in origin_lla)
        self.origin = geodetic_to_ecef(lat0, lon0, alt0)
        la, lo = np.radians(lat0), np.radians(lon0)
        east = np.array([-np.sin(lo), np.cos(lo), 0.0])
        north = np.array([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
        up = np.array([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
        self.basis = np.stack([east, north, up])  # rows: ENU unit vectors in ECEF

    def to_enu(self, lla) -> np.ndarray:
        """[lat, lon, alt] (..., 3) -> ENU metres (..., 3)."""
        lla = np.asarray(lla, dtype=float)
        d = geodetic_to_ecef(lla[..., 0], lla[..., 1], lla[..., 2]) - self.origin
        return d @ self.basis.T

    def to_lla(self, enu) -> np.ndarray:
        """ENU metres (..., 3) -> [lat, lon, alt] (..., 3)."""
        return ecef_to_geodetic(np.asarray(enu, dtype=float) @ self.basis + self.origin)
