"""Kernel side of the notebooks' render check: ``tests/_notebooks.py`` runs
:func:`install` in a hidden first cell of each notebook it executes and :func:`report`
in a hidden last one, so every figure a notebook shows (or saves) is checked with the
rules of ``tests/_figure_check.py``, as the test process checks the figures it saves.

Shown figures are checked where the kernel turns them into outputs: every figure
displayed, by the inline backend's flush after a cell, by ``plt.show()`` or
``fig.show()`` inside a cell, by ``display(fig)`` or as a cell's value, goes through
``get_ipython().display_formatter.format``, which :func:`install` wraps. A
``post_execute`` hook would run before the inline backend's flush (it is registered
before pyplot is imported) but misses the figures ``plt.show()`` has already shown
and closed inside the cell. Problems are recorded, with the number of cells run since
the one of :func:`install`, rather than raised (raised in the flush, they would only
print a traceback, not fail the cell); :func:`report` prints them after a marker for
``run_notebook``. Saved figures fail their cell at once (``Figure.savefig`` is
:func:`_figure_check.checked_savefig`).

The inline backend renders with ``bbox_inches="tight"`` (its default), which widens
the image to every text: there, as for ``savefig(..., bbox_inches="tight")``, text
beyond the figure canvas is not cut off.
"""

from __future__ import annotations

import json
import sys

from _figure_check import checked_savefig, figure_problems
from matplotlib.figure import Figure

MARKER = "@@heliojax-render-check@@ "
PROBLEMS: list[dict] = []
SHOWN = {"figures": 0}  # figures displayed (and checked)


def _inline_bbox_tight() -> bool:
    config = sys.modules.get("matplotlib_inline.config")
    if config is None:
        return False
    return config.InlineBackend.instance().print_figure_kwargs.get("bbox_inches") == "tight"


def _check(fig: Figure, cells_after_install: int) -> None:
    if not hasattr(fig.canvas, "get_renderer"):  # a bare Figure(), shown as a cell's value
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        FigureCanvasAgg(fig)
    try:
        found = figure_problems(fig)
    except Exception as e:  # reported as a problem of this figure
        found = [f"render check failed: {e!r}"]
    tight = _inline_bbox_tight()
    label = f"figure {fig.number}" if getattr(fig, "number", None) is not None else "figure"
    if fig.get_suptitle():
        label += f" ({fig.get_suptitle()[:40]!r})"
    for problem in found:
        if tight and problem.endswith("is cut off"):
            continue
        entry = {"cells_after_install": cells_after_install, "figure": label, "problem": problem}
        if entry not in PROBLEMS:  # a figure shown twice is reported once
            PROBLEMS.append(entry)


def install() -> None:
    """Check every figure the kernel displays from now on, and every one it saves."""
    from IPython import get_ipython

    ip = get_ipython()
    Figure.savefig = checked_savefig
    installed_at = ip.execution_count  # counts executions (by 1 per cell, stored in the history)
    display_format = ip.display_formatter.format

    def checked_format(obj, *args, **kwargs):
        if isinstance(obj, Figure):
            SHOWN["figures"] += 1
            _check(obj, ip.execution_count - installed_at)
        return display_format(obj, *args, **kwargs)

    ip.display_formatter.format = checked_format


def report() -> None:
    """Print the problems found so far and the number of figures checked after
    :data:`MARKER`, as JSON."""
    print(MARKER + json.dumps({"problems": PROBLEMS, "figures_checked": SHOWN["figures"]}))
