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
        file: path of the offending file (or a description such as ``"<memory>"``); a
            control character in it (a folder named with a line break) is escaped.
        field: dotted name of the offending field (``"motor_position.axis_1_motor_position"``),
            or ``None`` when the whole file is bad.
        reason: human-readable reason.
    """

    def __init__(self, file: str | os.PathLike | None, field: str | None, reason: str):
        self.file = None if file is None else _printable(str(file))
        self.field = None if field is None else _clip(_printable(field), MAX_FIELD_CHARS)
        self.reason = "\n".join(_clip(line, MAX_REASON_LINE_CHARS) for line in reason.split("\n"))
        field, reason = self.field, self.reason
        where = self.file if self.file is not None else "<unknown file>"
        if field is not None:
            where = f"{where}: field '{field}'"
        super().__init__(f"{where}: {reason}")

    def __reduce__(self):
        return (type(self), (self.file, self.field, self.reason))


MAX_FIELD_CHARS = 200
"""A field name longer than this (a JSON key of a megabyte) is shortened in messages."""
MAX_REASON_LINE_CHARS = 1000
"""A line of a reason longer than this (it quotes a value of a megabyte) is shortened."""


def _printable(text: str) -> str:
    """``text`` with control and other unprintable characters escaped (a key holding a
    line break would otherwise print as two lines of the message)."""
    return text if text.isprintable() else repr(text)[1:-1]


def _clip(text: str, limit: int) -> str:
    """``text``, or its head and tail with the middle left out, at most ``limit`` characters."""
    if len(text) <= limit:
        return text
    marker = f" ... [{len(text)} characters, the middle left out] ... "
    head = (limit - len(marker)) * 2 // 3
    tail = limit - len(marker) - head
    return text[:head] + marker + text[len(text) - tail :]


class ConfigError(HeliojaxError, ValueError):
    """Bad configuration (TOML file or command-line flags); its message is one line
    (:func:`one_line`: a path with a line break, a value of a megabyte)."""

    def __init__(self, message: str = "", *args: object):
        super().__init__(one_line(str(message)), *args)


def one_line(text: str, limit: int = MAX_REASON_LINE_CHARS) -> str:
    """``text`` as one line of a message: control characters escaped, at most ``limit``
    characters (the middle left out)."""
    return _clip(_printable(text), limit)


def few_names(names: list[str], shown: int = 5) -> str:
    """``names`` joined by commas for a message: at most ``shown`` of them and a count
    of the rest (``"A, B and 3 more"``)."""
    head = ", ".join(names[:shown])
    return head + (f" and {len(names) - shown} more" if len(names) > shown else "")
