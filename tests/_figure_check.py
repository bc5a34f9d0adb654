"""A render check for every figure the tests make: ``Figure.savefig`` is wrapped so
that each saved figure is first checked as a reader would look at it.

* every axes that shows data has an x and a y label (a colour bar: a label on its
  long axis), and every text (titles, labels, tick labels, legends, annotations)
  lies inside the figure canvas: nothing is cut off;
* an axes showing an image or a mesh with a colour map has a colour bar in the figure.

Figures the library saves (``heliojax._plotting.save_figure`` and the command
line's outputs) all go through ``savefig``, so the CLI, discovery, acceptance,
ray-tracing and reconstruction tests check their figures too.
"""

from __future__ import annotations

import matplotlib.collections as mcoll
import matplotlib.image as mimage
from matplotlib.figure import Figure

TOLERANCE_PX = 2.0


def _has_data(ax) -> bool:
    return bool(ax.lines or ax.patches or ax.collections or ax.images)


def _is_colorbar(ax) -> bool:
    return getattr(ax, "_colorbar", None) is not None


def _drawn_tick_labels(axis) -> list:
    """The tick labels ``axis`` draws: those of ticks inside its view limits (the
    locator's ticks beyond them keep labels that are never drawn)."""
    ticks = axis._update_ticks()  # noqa: SLF001 - the ticks Axis.draw draws
    return [label for tick in ticks for label in (tick.label1, tick.label2) if label.get_visible()]


def _mapped(ax) -> bool:
    artists = [*ax.images, *(c for c in ax.collections if isinstance(c, mcoll.QuadMesh))]
    return any(isinstance(a, mimage.AxesImage | mcoll.QuadMesh) and a.get_array() is not None for a in artists)


def figure_problems(fig: Figure) -> list[str]:
    """What a reader would miss in ``fig`` (empty: nothing)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()  # pyright: ignore[reportAttributeAccessIssue]
    box = fig.bbox
    problems = []
    colorbars = [ax for ax in fig.axes if _is_colorbar(ax)]
    for k, ax in enumerate(fig.axes):
        if not ax.get_visible():
            continue
        name = f"axes {k} ({ax.get_title() or 'untitled'})"
        if _is_colorbar(ax):
            if not (ax.get_ylabel() or ax.get_xlabel()):
                problems.append(f"{name}: colour bar without a label")
        elif _has_data(ax) and ax.axison:
            if not ax.get_xlabel():
                problems.append(f"{name}: no x label")
            if not ax.get_ylabel():
                problems.append(f"{name}: no y label")
            if _mapped(ax) and not colorbars:
                problems.append(f"{name}: image or mesh without a colour bar")
        texts = [ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label]  # noqa: SLF001
        texts += [t for t in _drawn_tick_labels(ax.xaxis) + _drawn_tick_labels(ax.yaxis) if t.get_text()]
        texts += list(ax.texts)
        legend = ax.get_legend()
        if legend is not None:
            texts += list(legend.get_texts())
        for t in texts:
            if not t.get_visible() or not t.get_text():
                continue
            e = t.get_window_extent(renderer)
            if (
                e.x0 < box.x0 - TOLERANCE_PX
                or e.y0 < box.y0 - TOLERANCE_PX
                or e.x1 > box.x1 + TOLERANCE_PX
                or e.y1 > box.y1 + TOLERANCE_PX
            ):
                problems.append(f"{name}: text {t.get_text()[:40]!r} is cut off")
    for t in fig.texts:
        e = t.get_window_extent(renderer)
        if t.get_text() and (e.x0 < -TOLERANCE_PX or e.x1 > box.x1 + TOLERANCE_PX or e.y1 > box.y1 + TOLERANCE_PX):
            problems.append(f"figure text {t.get_text()[:40]!r} is cut off")
    return problems


_original_savefig = Figure.savefig


def checked_savefig(self: Figure, fname, *args, **kwargs):
    """``Figure.savefig`` that first asserts :func:`figure_problems` is empty."""
    bbox_tight = kwargs.get("bbox_inches") == "tight"
    problems = [p for p in figure_problems(self) if not (bbox_tight and p.endswith("is cut off"))]
    assert not problems, f"figure {fname}: " + "; ".join(problems)
    return _original_savefig(self, fname, *args, **kwargs)
