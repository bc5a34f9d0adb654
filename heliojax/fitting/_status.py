"""Per-heliostat outcome codes of a fit."""

from __future__ import annotations

import enum


class FitStatus(enum.IntEnum):
    """Per-heliostat outcome of a fit.

    * ``CONVERGED`` - the solver met its tolerances.
    * ``MAX_STEPS`` - the step limit was reached first.
    * ``DIVERGED`` - the solver diverged or the result is not finite.
    * ``NON_FINITE_INPUT`` - a record selected for the fit holds NaN/inf.
    * ``TOO_FEW_RECORDS`` - fewer records than free parameters; never reported as a fit.
    * ``FAILED`` - any other solver failure.
    * ``NO_RECORDS`` - no record selected (a padding heliostat, or a split that
      leaves this heliostat nothing to train on).
    """

    CONVERGED = 0
    MAX_STEPS = 1
    DIVERGED = 2
    NON_FINITE_INPUT = 3
    TOO_FEW_RECORDS = 4
    FAILED = 5
    NO_RECORDS = 6

    @property
    def label(self) -> str:
        return self.name.lower()


__all__ = ["FitStatus"]
