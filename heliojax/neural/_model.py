"""The two neural models on top of a calibrated physics model.

*Residual* (:class:`NeuralCorrection`): a kinematic model whose joint angles are
the physics model's plus a learned correction of the motor counts' effect::

    angles(counts) = base.joint_angles(counts) + scale * net((counts - mid) / half_range)

``net`` is an :class:`MLP` ``2 -> 6-5-4-3 -> 2`` with a zero output layer, so the
untrained model *is* the physics model (bit for bit). It depends on the counts only
(no sun, no time), so it stays a kinematic model: :func:`heliojax.forward`,
:func:`heliojax.inverse_aim` and the beam error work on it unchanged.

*Paper* (:class:`PaperPredictor`, Pargmann et al.): two networks ``5 -> 6-5-4-3 -> 1``,
one per axis, map the sun and the focal-spot position on the target to the motor
counts that put the spot there. Inputs: the unit ENU sun vector ``(e, n, u)`` and the
spot's ENU east and up coordinates (all Jülich calibration targets are vertical
planes facing north, so (east, up) is the position on the target wall in one frame
common to the three targets), standardised; outputs: standardised counts.

Error of the paper variant (it predicts counts, not a pose): for a record with
counts ``c``, sun ``s`` and spot ``p``, the network predicts ``c_hat(s, p)``; the
error is the beam pointing error of the physics model at ``c_hat`` relative to the
*virtual spot* ``p* = O(c) + |p - O(c)| r(c)``, where ``O`` and ``r`` are the mirror
centre and reflected ray of the physics model at the recorded counts. That is the
angle by which the beam would move if the heliostat were driven to ``c_hat``
instead of ``c`` (the physics model only supplies the local counts-to-beam
sensitivity). For the physics model's own prediction ``c_hat = inverse_aim(p, s)``
it equals the model's beam error on the record to ~1e-5 relative (tested), so LM,
residual and paper errors are on one scale.
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._beam import beam_error_components, beam_pointing_error, reflected_ray
from .._geometry import normalize
from .._heliostat import HeliostatGeometry
from .._kinematics import AbstractKinematicModel, AbstractModelWrapper
from ._network import MLP


def _count_features(geometry: HeliostatGeometry, counts):
    a = geometry.actuators
    mid = 0.5 * (a.min_counts + a.max_counts)
    half = 0.5 * (a.max_counts - a.min_counts)
    return (counts - mid) / half


@typing.final
class NeuralCorrection(AbstractModelWrapper):
    """A model + learned joint-angle correction (the residual variant).

    A wrapper: every hook of the inner model (effects included) is kept, and the
    network's correction is added to the inner model's joint angles.

    Attributes:
        inner: the fitted model (:class:`heliojax.StoneModel`,
            :class:`heliojax.ActuatorModel`, an effect-wrapped model, ...).
        network: ``2 -> ... -> 2`` :class:`MLP` of the normalised counts.
        scale: rad per network output unit (scalar; ``(H,)`` when batched).
    """

    inner: AbstractKinematicModel
    network: MLP
    scale: Float[Array, "*h"]

    def label(self) -> str:
        return f"{self.inner.label()}+nn"

    def correction(self, geometry: HeliostatGeometry, counts: Float[Array, "2"]) -> Float[Array, "2"]:
        """Joint-angle correction (rad) at motor counts ``counts``."""
        counts = jnp.asarray(counts)
        out = self.network(_count_features(geometry, counts))
        return out.astype(counts.dtype) * self.scale

    def joint_angles(self, geometry, counts):
        return self.inner.joint_angles(geometry, counts) + self.correction(geometry, counts)

    def record_angles(self, geometry, counts, context):
        return self.inner.record_angles(geometry, counts, context) + self.correction(geometry, counts)

    def counts(self, geometry, angles, iterations: int = 4):
        """Inverse by fixed-point iteration on the (small, smooth) correction."""
        c = self.inner.counts(geometry, angles)
        for _ in range(iterations):
            c = self.inner.counts(geometry, angles - self.correction(geometry, c))
        return c


@typing.final
class PaperPredictor(eqx.Module):
    """Pargmann et al.'s network pair: (sun, focal spot) -> motor counts.

    Attributes:
        networks: two :class:`MLP` ``5 -> ... -> 1`` stacked along a leading axis
            (axis 1, axis 2).
        input_mean, input_std: ``(5,)`` standardisation of the features.
        output_mean, output_std: ``(2,)`` standardisation of the counts.
    """

    networks: MLP
    input_mean: Float[Array, " 5"]
    input_std: Float[Array, " 5"]
    output_mean: Float[Array, " 2"]
    output_std: Float[Array, " 2"]

    @staticmethod
    def features(sun: Float[Array, "*b 3"], spot: Float[Array, "*b 3"]) -> Float[Array, "*b 5"]:
        """Raw inputs: unit sun vector (e, n, u) and the spot's ENU east and up (m)."""
        return jnp.concatenate([sun, spot[..., jnp.asarray([0, 2])]], axis=-1)

    def standardised(self, sun, spot):
        return (self.features(sun, spot) - self.input_mean) / self.input_std

    def raw_output(self, sun, spot) -> Float[Array, " 2"]:
        """Standardised counts predicted for one record."""
        x = self.standardised(sun, spot)
        return jax.vmap(lambda net: net(x)[0])(self.networks)

    def __call__(self, sun: Float[Array, "3"], spot: Float[Array, "3"]) -> Float[Array, "2"]:
        """Motor counts predicted for sun ``sun`` (unit ENU) and spot ``spot`` (ENU m)."""
        y = self.raw_output(sun, spot).astype(self.output_mean.dtype)
        return y * self.output_std + self.output_mean


def virtual_spot(model: AbstractKinematicModel, geometry, counts, sun, focal_spot) -> Float[Array, "3"]:
    """Where the physics model at the recorded counts puts the beam, at the measured
    spot's distance (ENU m): ``O(c) + |p - O(c)| r(c)``."""
    pose = model.pose(geometry, counts)
    dist = jnp.linalg.norm(focal_spot - pose.centre)
    return pose.centre + dist * normalize(reflected_ray(pose, sun))


def paper_beam_error(model, geometry, counts, predicted, sun, focal_spot) -> Float[Array, ""]:
    """Beam error (rad) of predicted counts ``predicted`` for a record (see the module
    docstring): the physics model's beam at ``predicted`` against its beam at the
    recorded ``counts``."""
    target = virtual_spot(model, geometry, counts, sun, focal_spot)
    return beam_pointing_error(model.pose(geometry, predicted), sun, target)


def paper_beam_components(model, geometry, counts, predicted, sun, focal_spot) -> Float[Array, "2"]:
    """Tangent-plane components (rad) of :func:`paper_beam_error`."""
    target = virtual_spot(model, geometry, counts, sun, focal_spot)
    return beam_error_components(model.pose(geometry, predicted), sun, target)


__all__ = [
    "NeuralCorrection",
    "PaperPredictor",
    "paper_beam_components",
    "paper_beam_error",
    "virtual_spot",
]
