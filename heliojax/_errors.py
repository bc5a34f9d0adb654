"""Exception types of heliojax.

Every error that bad *input* can cause is a :class:`HeliojaxError`. Readers of
PAINT files raise :class:`DataError`, whose message names the file and the field.
"""

from __future__ import annotations

import os


class HeliojaxError(Exception):
    """Base class of all errors heliojax raises on purpose."""


class DataError(HeliojaxError, ValueError):
    """Bad input data: malformed file, missing / non-numeric / non-finite field.

    Attributes:
        file: path of the offending file (or a description such as ``"<memory>"``).
        field: dotted name of the offending field (``"motor_position.axis_1_motor_position"``),
            or ``None`` when the whole file is bad.
        reason: human-readable reason.
    """

    def __init__(self, file: str | os.PathLike | None, field: str | None, reason: str):
        self.file = None if file is None else str(file)
        self.field = field
        self.reason = reason
        where = self.file if self.file is not None else "<unknown file>"
        if field is not None:
            where = f"{where}: field '{field}'"
        super().__init__(f"{where}: {reason}")

    def __reduce__(self):
        return (type(self), (self.file, self.field, self.reason))


class ConfigError(HeliojaxError, ValueError):
    """Bad configuration (TOML file or command-line flags)."""
