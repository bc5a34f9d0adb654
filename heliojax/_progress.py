"""Progress of long work: messages through :mod:`logging` (loggers under
``"heliojax"``), bars through :mod:`tqdm`.

The library only logs; an application chooses what to show. The CLI shows INFO
messages on stderr (none with ``--quiet``); in Python,
``logging.basicConfig(level=logging.INFO)`` does the same. A bar is drawn only
when its logger is enabled for INFO and stderr is a terminal.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import typing
import weakref
from collections.abc import Iterable, Iterator

from tqdm import tqdm

T = typing.TypeVar("T")


class _Bar(tqdm):
    """A tqdm bar redrawn every ``refresh_s`` seconds from a helper thread, so that its
    elapsed time moves while one long item (a compiled call) runs. The thread holds
    the bar weakly and ends with :meth:`close`."""

    def __init__(self, *args: typing.Any, refresh_s: float = 0.5, **kwargs: typing.Any) -> None:
        self._stop_redraw = threading.Event()
        super().__init__(*args, **kwargs)
        if not self.disable:
            threading.Thread(
                target=_redraw, args=(weakref.ref(self), self._stop_redraw, refresh_s), daemon=True
            ).start()

    def close(self) -> None:
        self._stop_redraw.set()
        super().close()


def _redraw(bar_ref: weakref.ref, stop: threading.Event, refresh_s: float) -> None:
    while not stop.wait(refresh_s):
        bar = bar_ref()
        if bar is None:
            return
        bar.refresh()
        del bar


def progress_bar(
    items: Iterable[T] | None,
    *,
    logger: logging.Logger,
    desc: str,
    total: int | None = None,
    unit: str = "it",
    bar_format: str | None = None,
) -> tqdm:
    """``items`` with a progress bar on stderr (see the module docstring for when it
    is shown), redrawn twice a second; the bar disappears when done. With ``items``
    None, a bar of ``total`` steps advanced by its ``update()`` (use it as a context
    manager)."""
    shown = logger.isEnabledFor(logging.INFO)
    return _Bar(
        items,
        desc=desc,
        total=total,
        unit=unit,
        leave=False,
        dynamic_ncols=True,
        disable=None if shown else True,
        bar_format=bar_format,
    )


@contextlib.contextmanager
def activity(desc: str, *, logger: logging.Logger) -> Iterator[None]:
    """A bar without a count for one long step that cannot count its progress (one
    compiled call, a solve): the step's name and the time spent on it so far; shown
    under the same conditions as :func:`progress_bar`, gone when the step ends."""
    with progress_bar(None, logger=logger, desc=desc, bar_format="{desc}: {elapsed}"):
        yield


__all__ = ["activity", "progress_bar"]
