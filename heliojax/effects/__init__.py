"""Effect library: physical effects as composable extensions of a kinematic model.

An effect (:class:`AbstractEffect`) holds its own parameters and corrects one
stage of a record's prediction (geometry, joint angles, sun, focal spot).
:class:`EffectModel` ``(inner, effects)`` is again a kinematic model, so the
fit, the metrics and the simulator use it unchanged; :func:`with_effects`
wraps a model with named effects for :func:`heliojax.fit`.

The fixed list of effects (:data:`EFFECT_NAMES`):

==================== ===================================== ===================== ==========================
name                 parameters (units)                    driving inputs        residual signature
==================== ===================================== ===================== ==========================
``actuator_geometry`` ``curvature_1,2`` (1; stone8 base) or counts               curved in each axis's counts
                     ``pivot_scale_1,2`` (1; actuator base)
``backlash``         ``backlash_1,2`` (rad, dead-band width) approach directions   step between approach signs
                     or ``backlash_stroke_1,2`` (m; actuator
                     base: play in the stroke)
``thermal``          ``thermal_1,2`` (rad/K),               temperature           proportional to T - T_ref
                     ``thermal_scale_1,2`` (1/K)                                  (and to the angle; to the
                                                                                  stroke on an actuator base)
``wind``             ``wind_1,2``, ``wind_droop``           wind speed, direction v^2, by direction to mirror,
                     (rad/(m/s)^2)                                                and a tip toward the horizon
``clock``            ``clock_offset`` (s), ``clock_drift``  time, sun             sun turned about the pole,
                     (s/day)                                                      growing with time
``gravity_sag``      ``gravity_sag`` (rad)                  normal elevation      normal droops by ~cos(elevation)
``encoder_wobble``   ``wobble_cos/sin_1,2`` (rad), n = 2    joint angles          sinusoid of n * angle
``refraction``       ``refraction_scale`` (1)               sun elevation         vertical, ~cot(elevation)
``survey_heliostat`` ``survey_heliostat_e,n,u`` (m)         geometry              direction to target
``survey_target``    ``survey_target_<k>_e,n,u`` (m), one   the record's target   fixed shift on each target
                     per target slot k = 1..4
``offset_drift``     ``offset_drift_1,2`` (rad/year)        time                  offset growing with time
==================== ===================================== ===================== ==========================

Besides these, :class:`OffsetStep` (``change_point``: a jump of both joint zeros at
a date the change-point scan found) is added by discovery where a step is found;
it is not screened as a candidate.

Each class's docstring gives the physical meaning and the exact correction.
"""

from ._base import (
    AbstractEffect as AbstractEffect,
    EffectModel as EffectModel,
    add_effects as add_effects,
)
from ._environment import (
    SOLAR_RATE_RAD_S as SOLAR_RATE_RAD_S,
    YEAR_S as YEAR_S,
    Clock as Clock,
    OffsetDrift as OffsetDrift,
    OffsetStep as OffsetStep,
    Refraction as Refraction,
    Thermal as Thermal,
    Wind as Wind,
    standard_refraction as standard_refraction,
)
from ._mechanical import (
    ActuatorGeometry as ActuatorGeometry,
    Backlash as Backlash,
    EncoderWobble as EncoderWobble,
    GravitySag as GravitySag,
)
from ._spec import (
    EFFECT_CLASSES as EFFECT_CLASSES,
    EFFECT_NAMES as EFFECT_NAMES,
    data_references as data_references,
    effect_class as effect_class,
    make_effect as make_effect,
    with_data_references as with_data_references,
    with_effects as with_effects,
)
from ._survey import (
    TARGET_SLOTS as TARGET_SLOTS,
    SurveyHeliostat as SurveyHeliostat,
    SurveyTarget as SurveyTarget,
)
