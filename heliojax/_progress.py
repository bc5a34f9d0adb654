"""Progress of long work: messages through :mod:`logging` (loggers under
``"heliojax"``), bars through :mod:`tqdm`.

The library only logs; an application chooses what to show. The CLI shows INFO
messages on stderr (none with ``--quiet``); in Python,
``logging.basicConfig(level=logging.INFO)`` does the same. A bar is drawn only
when its logger is enabled for INFO and stderr is a terminal.
"""

from __future__ import annotations

import logging
import typing
from collections.abc import Iterable

from tqdm import tqdm

T = typing.TypeVar("T")


def progress_bar(
    items: Iterable[T] | None, *, logger: logging.Logger, desc: str, total: int | None = None, unit: str = "it"
) -> tqdm:
    """``items`` with a progress bar on stderr (see the module docstring for when it
    is shown); the bar disappears when done. With ``items`` None, a bar of ``total``
    steps advanced by its ``update()`` (use it as a context manager)."""
    shown = logger.isEnabledFor(logging.INFO)
    return tqdm(
        items, desc=desc, total=total, unit=unit, leave=False, dynamic_ncols=True, disable=None if shown else True
    )


__all__ = ["progress_bar"]
