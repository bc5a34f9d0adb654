"""Limits on inputs shared by the library and the command line, kept once: the span of
instants heliojax takes and the rule for a calibration target's name. The CLI reads them
when it parses its options (this module imports no JAX), so that an option is refused
by name instead of the library failing later with a traceback."""

from __future__ import annotations

import datetime as dt
import numbers
import typing

from ._io import SPREADSHEET_FORMULA_START, heliostat_id_problem

EARLIEST_UNIX_S = 0.0
"""1970-01-01T00:00Z (s): the first instant heliojax takes (Unix time 0)."""

LATEST_UNIX_S = 7_258_118_400.0
"""2200-01-01T00:00Z (s), itself excluded: a later instant is a time in other units
(milliseconds, nanoseconds given as seconds)."""


_SPAN = (EARLIEST_UNIX_S, LATEST_UNIX_S)

EARLIEST_YEAR = dt.datetime.fromtimestamp(EARLIEST_UNIX_S, dt.UTC).year
"""1970: the first year (UTC) whose every instant heliojax takes."""
LATEST_YEAR = dt.datetime.fromtimestamp(LATEST_UNIX_S - 1.0, dt.UTC).year
"""2199: the last year (UTC) whose every instant heliojax takes (``plan --envelope-year``
took 1900 to 2200, years of instants the library refuses)."""


def instant_problem(t: dt.datetime) -> str | None:
    """Why the instant ``t`` (naive: UTC) lies outside ``[EARLIEST_UNIX_S,
    LATEST_UNIX_S)``, the span :func:`heliojax.aim_results` takes, or None."""
    utc = t if t.tzinfo is not None else t.replace(tzinfo=dt.UTC)
    # a difference, not .timestamp() or .astimezone(): year 1 with an offset overflowed those
    seconds = (utc - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)).total_seconds()
    if EARLIEST_UNIX_S <= seconds < LATEST_UNIX_S:
        return None
    first, last = (dt.datetime.fromtimestamp(s, dt.UTC).strftime("%Y-%m-%dT%H:%MZ") for s in _SPAN)
    return f"outside the instants heliojax takes, {first} (included) to {last} (excluded), UTC"


def target_name_problem(name: object) -> str | None:
    """Why ``name`` cannot be a calibration target's name (a tower file's entry, a
    record's ``target_name``, ``--target``), or None: the rule of heliostat ids
    (:func:`heliojax._io.heliostat_id_problem`), since a target's name goes into the same
    CSV outputs (``heliojax plan``'s schedule): printable, not blank, no white space at
    either end, no ``,``, no path separator, at most 255 characters, and not starting
    with a spreadsheet formula's first character (``= + - @``)."""
    if not isinstance(name, str):
        return f"not a string ({type(name).__name__})"
    problem = heliostat_id_problem(name)
    if problem is not None and name.startswith(SPREADSHEET_FORMULA_START):  # named first: the gravest
        return f"starts with {name[0]!r} (a spreadsheet formula in a CSV cell)"  # (=HYPERLINK("a","b") holds a comma)
    return problem


MAX_SYNTHETIC_HELIOSTATS = 1_000_000
"""The most heliostats a synthetic fleet may have (the largest plants hold ~10^5): more
had been refused only by XLA running out of memory, after minutes."""

MAX_PLAN_BUDGET = 100_000
"""The most measurements per heliostat a plan may choose (``heliojax plan --budget`` takes
1,000): a budget of 10**9 had run a scan of 10**9 greedy steps."""

MAX_SYNTHETIC_RECORDS = 10_000_000
"""The most records (heliostats x records per heliostat) a synthetic fleet may have:
drawing their times takes ~1 kB each at its peak (13 candidate hours and their solar
positions), ~10 GB here."""


MAX_FIT_STEPS = 100_000
"""The most Levenberg-Marquardt steps one fit may take (:func:`heliojax.fit`'s
``max_steps``, ``calibrate --max-steps``, discovery's ``max_steps``; the default is 64):
``fit(max_steps=2**40)`` had been taken, a fleet that does not converge then running
for hours, and the command line took up to 2**31 - 1."""


MAX_FOLDS = 100
"""Most cross-validation folds of discovery: the fit runs once per fold and once on all
records, the fleet copied for each."""


def count_problem(value: object, limit: int, *, minimum: int = 1) -> str | None:
    """Why ``value`` cannot be a count (of heliostats, records, points) in
    ``[minimum, limit]``, or None: not an integer (a bool, a float, a string), below
    ``minimum`` or above ``limit`` (checked before anything is allocated)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        return f"must be a whole number, got {value!r} ({type(value).__name__})"
    n = int(value)
    if n < minimum:
        return f"must be at least {minimum}, got {n}"
    if n > limit:
        return f"must be at most {limit:,}, got {n:,}"
    return None


def real_problem(value: object, *, minimum: float | None = None) -> str | None:
    """Why ``value`` cannot be a real number (a magnitude, a width, a reference value)
    at least ``minimum`` (None: any), or None: a bool, a string, an array of more than
    one value, not finite (NaN had spread into every result without a word), or below
    ``minimum``. Callers skip traced values (unknown under ``jax.jit``)."""
    import numpy as np  # here: the CLI reads this module before anything imports NumPy

    expected = "a finite real number" if minimum is None else f"a finite number >= {minimum:g}"
    try:
        x: typing.Any = value
        ok = np.ndim(x) == 0 and not isinstance(x, (bool, np.bool_, str, bytes)) and bool(np.isfinite(x))
        ok = ok and (minimum is None or float(x) >= minimum)
    except (TypeError, ValueError):
        ok = False
    return None if ok else f"must be {expected}, got {value!r}"[:200]
