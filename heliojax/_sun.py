"""Sun position: the NREL Solar Position Algorithm (SPA) in JAX.

Reference:
    I. Reda and A. Andreas, "Solar Position Algorithm for Solar Radiation
    Applications", NREL/TP-560-34302, National Renewable Energy Laboratory,
    2003, revised January 2008. (Also Solar Energy 76(5), 577-589, 2004.)

The implementation follows the paper's steps 3.1-3.14 (Julian dates; Earth
heliocentric longitude, latitude and radius from the periodic terms of Table A4.2;
nutation from Table A4.3; aberration; apparent sidereal time; geocentric right
ascension and declination; parallax to topocentric coordinates; atmospheric
refraction; azimuth). The paper states an uncertainty of +/-0.0003 deg for
the years -2000 to 6000, given an exact ``delta_t``.

Conventions (heliojax / PAINT):
    * Angles are returned in **radians**; inputs at this boundary are in degrees,
      metres, seconds, hPa and degrees Celsius as named.
    * ``azimuth``: 0 = south, positive toward **east** (east = +pi/2, west = -pi/2),
      in (-pi, pi]. SPA's own azimuth Phi is measured eastward from north, so
      ``azimuth = pi - Phi`` wrapped to (-pi, pi]. The unit vector pointing to
      the sun in local ENU is ``(cos el sin az, -cos el cos az, sin el)``.
    * Times are UTC (UT1 ~ UTC, |UT1 - UTC| < 0.9 s) as seconds since the unix
      epoch 1970-01-01T00:00:00Z.

Precision:
    A unix time in float32 has a resolution of 128 s at the present epoch (about
    0.5 deg of sun motion), so **float64 is required for accuracy** (enable
    ``jax_enable_x64``). The functions compute in the dtype they are given; they
    warn (at trace time) when the time is not float64. Internally the time is
    referred to J2000.0 before the conversion to days, so no large Julian date
    is ever formed on the hot path.

Everything is jit-able, vmap-able and differentiable with respect to the time
and the location (the refraction branch is selected by ``jnp.where`` with a
clamped argument so that gradients stay finite below the horizon).
"""

from __future__ import annotations

import datetime as _dt
import functools
import typing
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float

__all__ = ["SolarPosition", "datetime_to_unix", "julian_day", "solar_position", "utc_datetime"]

# --------------------------------------------------------------------------------------
# Constants
# --------------------------------------------------------------------------------------

_UNIX_EPOCH_JD = 2440587.5  # Julian day of 1970-01-01T00:00:00 UTC
_J2000_JD = 2451545.0  # Julian day of 2000-01-01T12:00:00 (J2000.0)
_J2000_UNIX = 946728000.0  # unix seconds of J2000.0 (= (2451545 - 2440587.5) * 86400)
_SECONDS_PER_DAY = 86400.0
_SUN_RADIUS_DEG = 0.26667  # apparent radius of the sun, SPA step 3.14.1
_ATMOS_REFRACT_DEG = 0.5667  # refraction at sunrise/sunset assumed by SPA

# Earth periodic terms, Table A4.2 of Reda & Andreas (2008). Rows: (A, B, C) with the
# series term A * cos(B + C * JME); the result of a series sum is in 1e-8 rad (L, B)
# or 1e-8 AU (R).
_L0 = np.array(
    [
        [175347046.0, 0.0, 0.0],
        [3341656.0, 4.6692568, 6283.07585],
        [34894.0, 4.6261, 12566.1517],
        [3497.0, 2.7441, 5753.3849],
        [3418.0, 2.8289, 3.5231],
        [3136.0, 3.6277, 77713.7715],
        [2676.0, 4.4181, 7860.4194],
        [2343.0, 6.1352, 3930.2097],
        [1324.0, 0.7425, 11506.7698],
        [1273.0, 2.0371, 529.691],
        [1199.0, 1.1096, 1577.3435],
        [990.0, 5.233, 5884.927],
        [902.0, 2.045, 26.298],
        [857.0, 3.508, 398.149],
        [780.0, 1.179, 5223.694],
        [753.0, 2.533, 5507.553],
        [505.0, 4.583, 18849.228],
        [492.0, 4.205, 775.523],
        [357.0, 2.92, 0.067],
        [317.0, 5.849, 11790.629],
        [284.0, 1.899, 796.298],
        [271.0, 0.315, 10977.079],
        [243.0, 0.345, 5486.778],
        [206.0, 4.806, 2544.314],
        [205.0, 1.869, 5573.143],
        [202.0, 2.458, 6069.777],
        [156.0, 0.833, 213.299],
        [132.0, 3.411, 2942.463],
        [126.0, 1.083, 20.775],
        [115.0, 0.645, 0.98],
        [103.0, 0.636, 4694.003],
        [102.0, 0.976, 15720.839],
        [102.0, 4.267, 7.114],
        [99.0, 6.21, 2146.17],
        [98.0, 0.68, 155.42],
        [86.0, 5.98, 161000.69],
        [85.0, 1.3, 6275.96],
        [85.0, 3.67, 71430.7],
        [80.0, 1.81, 17260.15],
        [79.0, 3.04, 12036.46],
        [75.0, 1.76, 5088.63],
        [74.0, 3.5, 3154.69],
        [74.0, 4.68, 801.82],
        [70.0, 0.83, 9437.76],
        [62.0, 3.98, 8827.39],
        [61.0, 1.82, 7084.9],
        [57.0, 2.78, 6286.6],
        [56.0, 4.39, 14143.5],
        [56.0, 3.47, 6279.55],
        [52.0, 0.19, 12139.55],
        [52.0, 1.33, 1748.02],
        [51.0, 0.28, 5856.48],
        [49.0, 0.49, 1194.45],
        [41.0, 5.37, 8429.24],
        [41.0, 2.4, 19651.05],
        [39.0, 6.17, 10447.39],
        [37.0, 6.04, 10213.29],
        [37.0, 2.57, 1059.38],
        [36.0, 1.71, 2352.87],
        [36.0, 1.78, 6812.77],
        [33.0, 0.59, 17789.85],
        [30.0, 0.44, 83996.85],
        [30.0, 2.74, 1349.87],
        [25.0, 3.16, 4690.48],
    ]
)
_L1 = np.array(
    [
        [628331966747.0, 0.0, 0.0],
        [206059.0, 2.678235, 6283.07585],
        [4303.0, 2.6351, 12566.1517],
        [425.0, 1.59, 3.523],
        [119.0, 5.796, 26.298],
        [109.0, 2.966, 1577.344],
        [93.0, 2.59, 18849.23],
        [72.0, 1.14, 529.69],
        [68.0, 1.87, 398.15],
        [67.0, 4.41, 5507.55],
        [59.0, 2.89, 5223.69],
        [56.0, 2.17, 155.42],
        [45.0, 0.4, 796.3],
        [36.0, 0.47, 775.52],
        [29.0, 2.65, 7.11],
        [21.0, 5.34, 0.98],
        [19.0, 1.85, 5486.78],
        [19.0, 4.97, 213.3],
        [17.0, 2.99, 6275.96],
        [16.0, 0.03, 2544.31],
        [16.0, 1.43, 2146.17],
        [15.0, 1.21, 10977.08],
        [12.0, 2.83, 1748.02],
        [12.0, 3.26, 5088.63],
        [12.0, 5.27, 1194.45],
        [12.0, 2.08, 4694.0],
        [11.0, 0.77, 553.57],
        [10.0, 1.3, 6286.6],
        [10.0, 4.24, 1349.87],
        [9.0, 2.7, 242.73],
        [9.0, 5.64, 951.72],
        [8.0, 5.3, 2352.87],
        [6.0, 2.65, 9437.76],
        [6.0, 4.67, 4690.48],
    ]
)
_L2 = np.array(
    [
        [52919.0, 0.0, 0.0],
        [8720.0, 1.0721, 6283.0758],
        [309.0, 0.867, 12566.152],
        [27.0, 0.05, 3.52],
        [16.0, 5.19, 26.3],
        [16.0, 3.68, 155.42],
        [10.0, 0.76, 18849.23],
        [9.0, 2.06, 77713.77],
        [7.0, 0.83, 775.52],
        [5.0, 4.66, 1577.34],
        [4.0, 1.03, 7.11],
        [4.0, 3.44, 5573.14],
        [3.0, 5.14, 796.3],
        [3.0, 6.05, 5507.55],
        [3.0, 1.19, 242.73],
        [3.0, 6.12, 529.69],
        [3.0, 0.31, 398.15],
        [3.0, 2.28, 553.57],
        [2.0, 4.38, 5223.69],
        [2.0, 3.75, 0.98],
    ]
)
_L3 = np.array(
    [
        [289.0, 5.844, 6283.076],
        [35.0, 0.0, 0.0],
        [17.0, 5.49, 12566.15],
        [3.0, 5.2, 155.42],
        [1.0, 4.72, 3.52],
        [1.0, 5.3, 18849.23],
        [1.0, 5.97, 242.73],
    ]
)
_L4 = np.array([[114.0, 3.142, 0.0], [8.0, 4.13, 6283.08], [1.0, 3.84, 12566.15]])
_L5 = np.array([[1.0, 3.14, 0.0]])

_B0 = np.array(
    [
        [280.0, 3.199, 84334.662],
        [102.0, 5.422, 5507.553],
        [80.0, 3.88, 5223.69],
        [44.0, 3.7, 2352.87],
        [32.0, 4.0, 1577.34],
    ]
)
_B1 = np.array([[9.0, 3.9, 5507.55], [6.0, 1.73, 5223.69]])

_R0 = np.array(
    [
        [100013989.0, 0.0, 0.0],
        [1670700.0, 3.0984635, 6283.07585],
        [13956.0, 3.05525, 12566.1517],
        [3084.0, 5.1985, 77713.7715],
        [1628.0, 1.1739, 5753.3849],
        [1576.0, 2.8469, 7860.4194],
        [925.0, 5.453, 11506.77],
        [542.0, 4.564, 3930.21],
        [472.0, 3.661, 5884.927],
        [346.0, 0.964, 5507.553],
        [329.0, 5.9, 5223.694],
        [307.0, 0.299, 5573.143],
        [243.0, 4.273, 11790.629],
        [212.0, 5.847, 1577.344],
        [186.0, 5.022, 10977.079],
        [175.0, 3.012, 18849.228],
        [110.0, 5.055, 5486.778],
        [98.0, 0.89, 6069.78],
        [86.0, 5.69, 15720.84],
        [86.0, 1.27, 161000.69],
        [65.0, 0.27, 17260.15],
        [63.0, 0.92, 529.69],
        [57.0, 2.01, 83996.85],
        [56.0, 5.24, 71430.7],
        [49.0, 3.25, 2544.31],
        [47.0, 2.58, 775.52],
        [45.0, 5.54, 9437.76],
        [43.0, 6.01, 6275.96],
        [39.0, 5.36, 4694.0],
        [38.0, 2.39, 8827.39],
        [37.0, 0.83, 19651.05],
        [37.0, 4.9, 12139.55],
        [36.0, 1.67, 12036.46],
        [35.0, 1.84, 2942.46],
        [33.0, 0.24, 7084.9],
        [32.0, 0.18, 5088.63],
        [32.0, 1.78, 398.15],
        [28.0, 1.21, 6286.6],
        [28.0, 1.9, 6279.55],
        [26.0, 4.59, 10447.39],
    ]
)
_R1 = np.array(
    [
        [103019.0, 1.10749, 6283.07585],
        [1721.0, 1.0644, 12566.1517],
        [702.0, 3.142, 0.0],
        [32.0, 1.02, 18849.23],
        [31.0, 2.84, 5507.55],
        [25.0, 1.32, 5223.69],
        [18.0, 1.42, 1577.34],
        [10.0, 5.91, 10977.08],
        [9.0, 1.42, 6275.96],
        [9.0, 0.27, 5486.78],
    ]
)
_R2 = np.array(
    [
        [4359.0, 5.7846, 6283.0758],
        [124.0, 5.579, 12566.152],
        [12.0, 3.14, 0.0],
        [9.0, 3.63, 77713.77],
        [6.0, 1.87, 5573.14],
        [3.0, 5.47, 18849.23],
    ]
)
_R3 = np.array([[145.0, 4.273, 6283.076], [7.0, 3.92, 12566.15]])
_R4 = np.array([[4.0, 2.56, 6283.08]])

_L_SERIES = (_L0, _L1, _L2, _L3, _L4, _L5)
_B_SERIES = (_B0, _B1)
_R_SERIES = (_R0, _R1, _R2, _R3, _R4)

# Nutation, Table A4.3 of Reda & Andreas (2008). Columns Y0..Y4 multiply the arguments
# X0..X4 (mean elongation of the moon from the sun, mean anomaly of the sun, mean
# anomaly of the moon, moon's argument of latitude, longitude of the moon's ascending
# node); a, b, c, d in units of 0.0001 arcsec:
#   dpsi_i = (a + b JCE) sin(sum_j X_j Y_ij),  deps_i = (c + d JCE) cos(sum_j X_j Y_ij).
_NUTATION_Y = np.array(
    [
        [0, 0, 0, 0, 1],
        [-2, 0, 0, 2, 2],
        [0, 0, 0, 2, 2],
        [0, 0, 0, 0, 2],
        [0, 1, 0, 0, 0],
        [0, 0, 1, 0, 0],
        [-2, 1, 0, 2, 2],
        [0, 0, 0, 2, 1],
        [0, 0, 1, 2, 2],
        [-2, -1, 0, 2, 2],
        [-2, 0, 1, 0, 0],
        [-2, 0, 0, 2, 1],
        [0, 0, -1, 2, 2],
        [2, 0, 0, 0, 0],
        [0, 0, 1, 0, 1],
        [2, 0, -1, 2, 2],
        [0, 0, -1, 0, 1],
        [0, 0, 1, 2, 1],
        [-2, 0, 2, 0, 0],
        [0, 0, -2, 2, 1],
        [2, 0, 0, 2, 2],
        [0, 0, 2, 2, 2],
        [0, 0, 2, 0, 0],
        [-2, 0, 1, 2, 2],
        [0, 0, 0, 2, 0],
        [-2, 0, 0, 2, 0],
        [0, 0, -1, 2, 1],
        [0, 2, 0, 0, 0],
        [2, 0, -1, 0, 1],
        [-2, 2, 0, 2, 2],
        [0, 1, 0, 0, 1],
        [-2, 0, 1, 0, 1],
        [0, -1, 0, 0, 1],
        [0, 0, 2, -2, 0],
        [2, 0, -1, 2, 1],
        [2, 0, 1, 2, 2],
        [0, 1, 0, 2, 2],
        [-2, 1, 1, 0, 0],
        [0, -1, 0, 2, 2],
        [2, 0, 0, 2, 1],
        [2, 0, 1, 0, 0],
        [-2, 0, 2, 2, 2],
        [-2, 0, 1, 2, 1],
        [2, 0, -2, 0, 1],
        [2, 0, 0, 0, 1],
        [0, -1, 1, 0, 0],
        [-2, -1, 0, 2, 1],
        [-2, 0, 0, 0, 1],
        [0, 0, 2, 2, 1],
        [-2, 0, 2, 0, 1],
        [-2, 1, 0, 2, 1],
        [0, 0, 1, -2, 0],
        [-1, 0, 1, 0, 0],
        [-2, 1, 0, 0, 0],
        [1, 0, 0, 0, 0],
        [0, 0, 1, 2, 0],
        [0, 0, -2, 2, 2],
        [-1, -1, 1, 0, 0],
        [0, 1, 1, 0, 0],
        [0, -1, 1, 2, 2],
        [2, -1, -1, 2, 2],
        [0, 0, 3, 2, 2],
        [2, -1, 0, 2, 2],
    ],
    dtype=np.float64,
)
_NUTATION_ABCD = np.array(
    [
        [-171996, -174.2, 92025, 8.9],
        [-13187, -1.6, 5736, -3.1],
        [-2274, -0.2, 977, -0.5],
        [2062, 0.2, -895, 0.5],
        [1426, -3.4, 54, -0.1],
        [712, 0.1, -7, 0],
        [-517, 1.2, 224, -0.6],
        [-386, -0.4, 200, 0],
        [-301, 0, 129, -0.1],
        [217, -0.5, -95, 0.3],
        [-158, 0, 0, 0],
        [129, 0.1, -70, 0],
        [123, 0, -53, 0],
        [63, 0, 0, 0],
        [63, 0.1, -33, 0],
        [-59, 0, 26, 0],
        [-58, -0.1, 32, 0],
        [-51, 0, 27, 0],
        [48, 0, 0, 0],
        [46, 0, -24, 0],
        [-38, 0, 16, 0],
        [-31, 0, 13, 0],
        [29, 0, 0, 0],
        [29, 0, -12, 0],
        [26, 0, 0, 0],
        [-22, 0, 0, 0],
        [21, 0, -10, 0],
        [17, -0.1, 0, 0],
        [16, 0, -8, 0],
        [-16, 0.1, 7, 0],
        [-15, 0, 9, 0],
        [-13, 0, 7, 0],
        [-12, 0, 6, 0],
        [11, 0, 0, 0],
        [-10, 0, 5, 0],
        [-8, 0, 3, 0],
        [7, 0, -3, 0],
        [-7, 0, 0, 0],
        [-7, 0, 3, 0],
        [-7, 0, 3, 0],
        [6, 0, 0, 0],
        [6, 0, -3, 0],
        [6, 0, -3, 0],
        [-6, 0, 3, 0],
        [-6, 0, 3, 0],
        [5, 0, 0, 0],
        [-5, 0, 3, 0],
        [-5, 0, 3, 0],
        [-5, 0, 3, 0],
        [4, 0, 0, 0],
        [4, 0, 0, 0],
        [4, 0, 0, 0],
        [-4, 0, 0, 0],
        [-4, 0, 0, 0],
        [-4, 0, 0, 0],
        [3, 0, 0, 0],
        [-3, 0, 0, 0],
        [-3, 0, 0, 0],
        [-3, 0, 0, 0],
        [-3, 0, 0, 0],
        [-3, 0, 0, 0],
        [-3, 0, 0, 0],
        [-3, 0, 0, 0],
    ],
    dtype=np.float64,
)

# Polynomials (degrees, in JCE) of the nutation arguments X0..X4, SPA eqs. 15-19:
# rows are the coefficients of JCE^0, JCE^1, JCE^2, JCE^3.
_NUTATION_X_POLY = np.array(
    [
        [297.85036, 445267.111480, -0.0019142, 1.0 / 189474.0],
        [357.52772, 35999.050340, -0.0001603, -1.0 / 300000.0],
        [134.96298, 477198.867398, 0.0086972, 1.0 / 56250.0],
        [93.27191, 483202.017538, -0.0036825, 1.0 / 327270.0],
        [125.04452, -1934.136261, 0.0020708, 1.0 / 450000.0],
    ]
)

# Mean obliquity of the ecliptic (arcsec) as a polynomial in U = JME / 10, SPA eq. 24,
# coefficients of U^0 .. U^10.
_OBLIQUITY_POLY = np.array([84381.448, -4680.93, -1.55, 1999.25, -51.38, -249.67, -39.05, 7.12, 27.87, 5.79, 2.45])


# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


@typing.final
class SolarPosition(eqx.Module):
    """Topocentric position of the sun (all angles in radians, same shape ``...``).

    Attributes:
        azimuth: 0 = south, positive toward east (east = +pi/2), in (-pi, pi].
        elevation: topocentric elevation angle above the horizon, including the
            atmospheric refraction correction when it was requested.
        zenith: ``pi/2 - elevation``.
        declination: topocentric declination of the sun (delta').
        hour_angle: topocentric local hour angle (H'), positive toward west
            (afternoon), in (-pi, pi].
        equation_of_time_min: equation of time (apparent minus mean solar time), minutes.
    """

    azimuth: Float[Array, "..."]
    elevation: Float[Array, "..."]
    zenith: Float[Array, "..."]
    declination: Float[Array, "..."]
    hour_angle: Float[Array, "..."]
    equation_of_time_min: Float[Array, "..."]

    def direction_enu(self) -> Float[Array, "... 3"]:
        """Unit vector pointing to the sun in the local east-north-up frame, shape ``(..., 3)``."""
        ce = jnp.cos(self.elevation)
        return jnp.stack(
            [ce * jnp.sin(self.azimuth), -ce * jnp.cos(self.azimuth), jnp.sin(self.elevation)],
            axis=-1,
        )


def julian_day(unix_time_s: ArrayLike) -> Float[Array, "..."]:
    """Julian day (UT) of a unix time.

    Args:
        unix_time_s: seconds since 1970-01-01T00:00:00Z, any shape. Use float64: a Julian
            day near 2.46e6 in float32 has a resolution of about 4 minutes.

    Returns:
        Julian day, same shape and floating dtype as the input (ints become the default
        float dtype).
    """
    t = _as_float(unix_time_s)
    return t / _SECONDS_PER_DAY + _UNIX_EPOCH_JD


@typing.no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def utc_datetime(value: _dt.datetime | str) -> _dt.datetime:
    """The one reading of a date-time (a data file's, a STAC item's, a command line's)
    as an aware UTC :class:`datetime.datetime`.

    PAINT's convention: every PAINT time is UTC. PAINT writes its times as
    ``%Y-%m-%dT%H:%M:%SZ`` (``TIME_FORMAT`` of ``paint/util/paint_mappings.py``) and,
    since PAINT 3.0 ("time stamp conversion from local time to UTC has been
    clarified", PR 129), localises the database's times as UTC
    (``paint.util.utils.localize_utc``), not as Jülich's local time. So a time
    **without a zone is UTC** (not this machine's local time, not Europe/Berlin), and
    one with an offset (``+02:00``) is converted to UTC.

    Args:
        value: a :class:`datetime.datetime` or an ISO-8601 string such as
            ``"2022-06-10T12:15:59Z"`` or ``"2022-06-10 14:15:59+02:00"``.

    Raises:
        ValueError: if the string is not ISO-8601, or the instant in UTC falls outside
            the years 1-9999 (``9999-12-31T23:00-05:00``).
        TypeError: for any other input type.
    """
    if isinstance(value, str):
        text = value.strip()
        if text.endswith(("Z", "z")):
            text = text[:-1] + "+00:00"
        try:
            dt = _dt.datetime.fromisoformat(text)
        except ValueError as err:
            raise ValueError(f"not an ISO-8601 date-time: {value!r}") from err
    elif isinstance(value, _dt.datetime):
        dt = value
    else:
        raise TypeError(f"expected a datetime or an ISO-8601 string, got {type(value).__name__}")
    if dt.tzinfo is None:
        return dt.replace(tzinfo=_dt.UTC)  # PAINT's convention, see above
    try:
        return dt.astimezone(_dt.UTC)
    except OverflowError:  # a year-1 or year-9999 time whose offset carries it out of datetime's range
        raise ValueError(f"{value!r} in UTC falls outside the years 1-9999") from None


@typing.no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def datetime_to_unix(dt_or_iso_string: _dt.datetime | str) -> float:
    """Seconds since the unix epoch of a UTC instant (data-boundary helper, not traceable).

    Args:
        dt_or_iso_string: a :class:`datetime.datetime` or an ISO-8601 string such as
            ``"2022-06-10T12:15:59Z"`` or ``"2022-06-10 14:15:59+02:00"``, read by
            :func:`utc_datetime`: one without offset is **UTC** (PAINT's convention).

    Returns:
        Unix time in seconds (Python float, exact to the microsecond).

    Raises:
        ValueError: if the string is not ISO-8601.
        TypeError: for any other input type.
    """
    delta = utc_datetime(dt_or_iso_string) - _dt.datetime(1970, 1, 1, tzinfo=_dt.UTC)
    # Exact integer arithmetic before the single rounding to float.
    micro = (delta.days * 86400 + delta.seconds) * 1_000_000 + delta.microseconds
    return micro / 1e6


SPA_VALID_UNIX_S = (-125_000_000_000.0, 127_000_000_000.0)
"""Unix times (s) of SPA's validity, the years -2000 to 6000 (Reda & Andreas 2008), rounded inwards."""


def _seconds_since_1970(value: typing.Any) -> typing.Any:
    """``value`` as seconds since 1970 (a numpy ``datetime64`` converted; NaT is NaN),
    checked where it is concrete; a tracer is returned as it is."""
    if isinstance(value, Tracer):
        return value
    if isinstance(value, str | bytes) or np.asarray(value).dtype.kind in "USO":
        text = isinstance(value, str | bytes) or np.asarray(value).dtype.kind in "US"
        what = f"text {value!r}" if text else f"{type(value).__name__} {value!r}"  # a datetime is no text
        raise TypeError(
            f"unix_time_s must be seconds since 1970-01-01 UTC, not {what:.200} "
            "(heliojax.datetime_to_unix converts a datetime or an ISO 8601 string)"
        )
    array = np.asarray(value)
    if array.dtype.kind == "M":
        ns = array.astype("datetime64[ns]")
        value = np.where(np.isnat(ns), np.nan, ns.astype(np.int64) / 1e9)
        array = value
    if array.dtype.kind in "biuf":
        t = np.asarray(array, float)
        lo, hi = SPA_VALID_UNIX_S
        if np.any((t < lo) | (t > hi)):  # NaN: NaN out
            raise ValueError(
                "unix_time_s must be seconds since 1970-01-01 UTC within the years -2000 to 6000 that SPA covers, "
                f"not {t[(t < lo) | (t > hi)].ravel()[0]:.6g} (milliseconds or nanoseconds?)"
            )
    return value


def solar_position(
    unix_time_s: ArrayLike,
    latitude_deg: ArrayLike,
    longitude_deg: ArrayLike,
    altitude_m: ArrayLike = 0.0,
    *,
    pressure_hpa: ArrayLike = 1013.25,
    temperature_c: ArrayLike = 12.0,
    delta_t_s: ArrayLike = 69.0,
    refraction: bool = True,
) -> SolarPosition:
    """Topocentric sun position by the NREL SPA (Reda & Andreas 2008), in JAX.

    All array arguments broadcast against each other; the outputs have the broadcast
    shape ``...``. jit-able, vmap-able and differentiable (e.g. ``jax.grad`` of the
    elevation with respect to ``unix_time_s``).

    Args:
        unix_time_s: UTC instant, seconds since 1970-01-01T00:00:00Z. **Needs float64**
            for accuracy (float32 resolves only 128 s today; a warning is issued).
        latitude_deg: geodetic latitude, degrees, north positive.
        longitude_deg: longitude, degrees, east positive.
        altitude_m: height above the WGS84 ellipsoid / sea level, metres (parallax term).
        pressure_hpa: local air pressure, hPa (= mbar); refraction only.
        temperature_c: local air temperature, degrees Celsius; refraction only.
        delta_t_s: Delta T = TT - UT1, seconds (about 69.2 s in 2022-2024).
        refraction: add SPA's refraction correction to the elevation (applied only while
            the refraction-free elevation is above -0.8334 deg, as in SPA).

    Returns:
        :class:`SolarPosition` with angles in radians; azimuth 0 = south, east positive.

    Raises:
        ValueError: a (concrete) latitude outside [-90, 90] deg or a longitude outside
            [-360, 360] deg (radians or a swapped pair), a (concrete) time outside
            the years -2000 to 6000 that SPA covers (milliseconds or nanoseconds since
            1970 gave a plausible sun of the wrong year), a negative pressure or a
            temperature below absolute zero (each had given a refraction without a
            word); under jit not checked.
        TypeError: times given as text (:func:`datetime_to_unix` converts them); another
            argument that is no array of real numbers (a string had failed inside JAX,
            None or a complex number in NumPy, ``True`` had been 1 degree), or a
            ``refraction`` that is not True or False (``"no"`` had applied it).
    """
    unix_time_s = _seconds_since_1970(unix_time_s)
    if not isinstance(refraction, (bool, np.bool_)):
        raise TypeError(f"solar_position: refraction must be True or False, got {refraction!r}"[:200])
    for name, value, low, high in (
        ("latitude_deg", latitude_deg, -90.0, 90.0),
        ("longitude_deg", longitude_deg, -360.0, 360.0),
        ("altitude_m", altitude_m, -np.inf, np.inf),
        ("pressure_hpa", pressure_hpa, 0.0, np.inf),
        ("temperature_c", temperature_c, -273.15, np.inf),
        ("delta_t_s", delta_t_s, -np.inf, np.inf),
    ):
        if isinstance(value, Tracer):
            continue
        kind = "?" if value is None or isinstance(value, (str, bytes)) else np.asarray(value).dtype.kind
        if kind not in "iuf":
            raise TypeError(f"solar_position: {name} must be real numbers, got {type(value).__name__} {value!r}"[:200])
        x = np.asarray(value, float)
        if np.any((x < low) | (x > high)):  # NaN: NaN out
            raise ValueError(f"{name} must be in [{low:g}, {high:g}], not {value!r}"[:200])
    s = _spa(
        unix_time_s,
        latitude_deg,
        longitude_deg,
        altitude_m,
        pressure_hpa=pressure_hpa,
        temperature_c=temperature_c,
        delta_t_s=delta_t_s,
        refraction=refraction,
    )
    return SolarPosition(
        azimuth=s["azimuth"],
        elevation=s["elevation"],
        zenith=s["zenith"],
        declination=s["declination"],
        hour_angle=s["hour_angle"],
        equation_of_time_min=s["equation_of_time_min"],
    )


# --------------------------------------------------------------------------------------
# Implementation
# --------------------------------------------------------------------------------------


def _as_float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))  # float64 under x64, else float32
    return x


def _wrap_deg(x: Array) -> Array:
    """Degrees to (-180, 180]."""
    return 180.0 - jnp.mod(180.0 - x, 360.0)


def _series(table: np.ndarray, jme: Array) -> Array:
    """Sum of A cos(B + C JME) over the rows of ``table``; shape of ``jme``."""
    shape = (1,) * jnp.ndim(jme) + (table.shape[0],)
    a, b, c = (jnp.asarray(table[:, k], dtype=jme.dtype).reshape(shape) for k in range(3))
    return jnp.sum(a * jnp.cos(b + c * jme[..., None]), axis=-1)


def _poly(coeffs: list, x: Array) -> Array:
    """sum_i coeffs[i] x^i by Horner's rule."""
    out = coeffs[-1]
    for c in reversed(coeffs[:-1]):
        out = out * x + c
    return out


def _earth_heliocentric(jme: Array) -> tuple[Array, Array, Array]:
    """Earth heliocentric longitude L (deg, [0, 360)), latitude B (deg), radius R (AU)."""
    lon = _poly([_series(t, jme) for t in _L_SERIES], jme) / 1e8
    lat = _poly([_series(t, jme) for t in _B_SERIES], jme) / 1e8
    rad = _poly([_series(t, jme) for t in _R_SERIES], jme) / 1e8
    return jnp.mod(jnp.rad2deg(lon), 360.0), jnp.rad2deg(lat), rad


def _nutation(jce: Array) -> tuple[Array, Array]:
    """Nutation in longitude and in obliquity (delta psi, delta epsilon), degrees."""
    lead = (1,) * jnp.ndim(jce)  # explicit broadcasting of the tables over jce's shape
    poly = jnp.asarray(_NUTATION_X_POLY, dtype=jce.dtype).reshape(-1, 4)
    x = _poly([poly[:, k].reshape(lead + (-1,)) for k in range(4)], jce[..., None])  # (..., 5), degrees
    arg = jnp.deg2rad(x @ jnp.asarray(_NUTATION_Y.T, dtype=jce.dtype))  # (..., 63)
    abcd = jnp.asarray(_NUTATION_ABCD, dtype=jce.dtype).reshape(lead + (-1, 4))
    abcd = [abcd[..., k] for k in range(4)]
    j = jce[..., None]
    dpsi = jnp.sum((abcd[0] + abcd[1] * j) * jnp.sin(arg), axis=-1) / 36_000_000.0
    deps = jnp.sum((abcd[2] + abcd[3] * j) * jnp.cos(arg), axis=-1) / 36_000_000.0
    return dpsi, deps


def _spa(
    unix_time_s: ArrayLike,
    latitude_deg: ArrayLike,
    longitude_deg: ArrayLike,
    altitude_m: ArrayLike = 0.0,
    *,
    pressure_hpa: ArrayLike = 1013.25,
    temperature_c: ArrayLike = 12.0,
    delta_t_s: ArrayLike = 69.0,
    refraction: bool = True,
    atmos_refract_deg: float = _ATMOS_REFRACT_DEG,
) -> dict[str, Array]:
    """All SPA quantities (the paper's symbols; degrees unless the key says otherwise).

    Also the float32 warning lives here (outside the compiled part, so it fires per call).

    Keys of the paper's worked example (Table A5.1): ``jd, L, B, R, dpsi, deps, eps,
    lamda, alpha, delta, H, alpha_p, delta_p, H_p, e0, zenith_deg, azimuth_spa_deg, eot``;
    plus the radian outputs of :class:`SolarPosition`.
    """
    t = _as_float(unix_time_s)
    if jnp.finfo(t.dtype).bits < 64:
        warnings.warn(
            f"solar_position: unix time in {t.dtype} resolves only ~"
            f"{float(np.spacing(np.asarray(1.7e9, t.dtype))):.0f} s today (about 0.5 deg of "
            "sun motion); pass float64 times with jax_enable_x64 for SPA accuracy",
            stacklevel=3,
        )
    return _spa_jit(
        t,
        latitude_deg,
        longitude_deg,
        altitude_m,
        pressure_hpa=pressure_hpa,
        temperature_c=temperature_c,
        delta_t_s=delta_t_s,
        refraction=refraction,
        atmos_refract_deg=atmos_refract_deg,
    )


@functools.partial(jax.jit, static_argnames=("refraction", "atmos_refract_deg"))
def _spa_jit(
    t: Array,
    latitude_deg: ArrayLike,
    longitude_deg: ArrayLike,
    altitude_m: ArrayLike,
    *,
    pressure_hpa: ArrayLike,
    temperature_c: ArrayLike,
    delta_t_s: ArrayLike,
    refraction: bool,
    atmos_refract_deg: float,
) -> dict[str, Array]:
    # Compiled once per shape/dtype: eager use stays fast, and inside a caller's jit,
    # vmap or grad this is an ordinary nested jit.
    dtype = jnp.result_type(t, latitude_deg, longitude_deg, altitude_m)
    t = t.astype(dtype)
    lat = jnp.asarray(latitude_deg, dtype)
    lon = jnp.asarray(longitude_deg, dtype)
    alt = jnp.asarray(altitude_m, dtype)
    pressure = jnp.asarray(pressure_hpa, dtype)
    temperature = jnp.asarray(temperature_c, dtype)
    delta_t = jnp.asarray(delta_t_s, dtype)
    t, lat, lon, alt, pressure, temperature, delta_t = jnp.broadcast_arrays(
        t, lat, lon, alt, pressure, temperature, delta_t
    )

    # 3.1 Julian dates, referred to J2000.0 (days) to keep float64 precision.
    d = (t - _J2000_UNIX) / _SECONDS_PER_DAY  # JD - 2451545
    de = d + delta_t / _SECONDS_PER_DAY  # JDE - 2451545
    jc = d / 36525.0
    jce = de / 36525.0
    jme = jce / 10.0

    # 3.2 Earth heliocentric position; 3.3 geocentric.
    L, B, R = _earth_heliocentric(jme)
    theta = jnp.mod(L + 180.0, 360.0)
    beta = -B

    # 3.4 nutation; 3.5 obliquity.
    dpsi, deps = _nutation(jce)
    u = jme / 10.0
    eps0 = _poly([float(c) for c in _OBLIQUITY_POLY], u)  # arcsec
    eps = eps0 / 3600.0 + deps

    # 3.6 aberration; 3.7 apparent sun longitude.
    dtau = -20.4898 / (3600.0 * R)
    lamda = theta + dpsi + dtau

    # 3.8 apparent sidereal time at Greenwich.
    nu0 = jnp.mod(280.46061837 + 360.98564736629 * d + 0.000387933 * jc**2 - jc**3 / 38710000.0, 360.0)
    eps_r = jnp.deg2rad(eps)
    nu = nu0 + dpsi * jnp.cos(eps_r)

    # 3.9-3.10 geocentric right ascension and declination.
    lam_r, beta_r = jnp.deg2rad(lamda), jnp.deg2rad(beta)
    alpha = jnp.mod(
        jnp.rad2deg(
            jnp.arctan2(
                jnp.sin(lam_r) * jnp.cos(eps_r) - jnp.tan(beta_r) * jnp.sin(eps_r),
                jnp.cos(lam_r),
            )
        ),
        360.0,
    )
    delta = jnp.rad2deg(
        jnp.arcsin(jnp.sin(beta_r) * jnp.cos(eps_r) + jnp.cos(beta_r) * jnp.sin(eps_r) * jnp.sin(lam_r))
    )

    # 3.11 observer local hour angle (westward from south).
    H = jnp.mod(nu + lon - alpha, 360.0)

    # 3.12 topocentric right ascension / declination (parallax).
    xi = jnp.deg2rad(8.794 / (3600.0 * R))
    lat_r = jnp.deg2rad(lat)
    uu = jnp.arctan(0.99664719 * jnp.tan(lat_r))
    x = jnp.cos(uu) + alt / 6378140.0 * jnp.cos(lat_r)
    y = 0.99664719 * jnp.sin(uu) + alt / 6378140.0 * jnp.sin(lat_r)
    H_r, delta_r = jnp.deg2rad(H), jnp.deg2rad(delta)
    den = jnp.cos(delta_r) - x * jnp.sin(xi) * jnp.cos(H_r)
    dalpha_r = jnp.arctan2(-x * jnp.sin(xi) * jnp.sin(H_r), den)
    alpha_p = alpha + jnp.rad2deg(dalpha_r)
    delta_p_r = jnp.arctan2((jnp.sin(delta_r) - y * jnp.sin(xi)) * jnp.cos(dalpha_r), den)

    # 3.13 topocentric local hour angle.
    H_p = H - jnp.rad2deg(dalpha_r)
    Hp_r = jnp.deg2rad(H_p)

    # 3.14 topocentric elevation, refraction, zenith.
    e0 = jnp.rad2deg(
        jnp.arcsin(jnp.sin(lat_r) * jnp.sin(delta_p_r) + jnp.cos(lat_r) * jnp.cos(delta_p_r) * jnp.cos(Hp_r))
    )
    if refraction:
        limit = -(_SUN_RADIUS_DEG + atmos_refract_deg)
        e0c = jnp.maximum(e0, limit)  # keeps the unselected branch (and its gradient) finite
        de_refr = (
            (pressure / 1010.0)
            * (283.0 / (273.0 + temperature))
            * 1.02
            / (60.0 * jnp.tan(jnp.deg2rad(e0c + 10.3 / (e0c + 5.11))))
        )
        e = e0 + jnp.where(e0 >= limit, de_refr, jnp.zeros_like(de_refr))
    else:
        e = e0
    zenith_deg = 90.0 - e

    # 3.15 azimuth. Astronomers' azimuth Gamma (westward from south); heliojax azimuth is
    # eastward from south = -Gamma. The form below is Gamma's atan2 times cos(delta') > 0.
    az = jnp.arctan2(
        -jnp.sin(Hp_r) * jnp.cos(delta_p_r),
        jnp.sin(lat_r) * jnp.cos(delta_p_r) * jnp.cos(Hp_r) - jnp.cos(lat_r) * jnp.sin(delta_p_r),
    )
    azimuth_spa_deg = jnp.mod(180.0 - jnp.rad2deg(az), 360.0)  # eastward from north

    # A.1 equation of time (minutes).
    M = _poly(
        [280.4664567, 360007.6982779, 0.03032028, 1.0 / 49931.0, -1.0 / 15300.0, -1.0 / 2e6], jme
    )  # sun's mean longitude, degrees
    eot = 4.0 * _wrap_deg(M - 0.0057183 - alpha + dpsi * jnp.cos(eps_r))

    return {
        "jd": d + _J2000_JD,
        "jde": de + _J2000_JD,
        "L": L,
        "B": B,
        "R": R,
        "theta": theta,
        "beta": beta,
        "dpsi": dpsi,
        "deps": deps,
        "eps0": eps0,
        "eps": eps,
        "dtau": dtau,
        "lamda": lamda,
        "nu0": nu0,
        "nu": nu,
        "alpha": alpha,
        "delta": delta,
        "H": H,
        "alpha_p": alpha_p,
        "delta_p": jnp.rad2deg(delta_p_r),
        "H_p": H_p,
        "e0": e0,
        "e": e,
        "zenith_deg": zenith_deg,
        "azimuth_spa_deg": azimuth_spa_deg,
        "M": M,
        "eot": eot,
        # radian outputs (heliojax conventions)
        "azimuth": az,
        "elevation": jnp.deg2rad(e),
        "zenith": jnp.deg2rad(zenith_deg),
        "declination": delta_p_r,
        "hour_angle": jnp.deg2rad(_wrap_deg(H_p)),
        "equation_of_time_min": eot,
    }
