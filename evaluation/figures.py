"""Figures without pyplot: the reports draw on ``matplotlib.figure.Figure`` objects, so writing a
report from a notebook neither switches the user's matplotlib backend (``matplotlib.use("Agg")`` did,
for the whole process: inline figures stopped showing) nor adds figures to pyplot's registry."""

from __future__ import annotations


def subplots(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float], constrained_layout: bool = False,
             squeeze: bool = True):
    """``pyplot.subplots`` on a detached Figure: (figure, axes). ``figure.savefig`` writes a PNG with
    matplotlib's Agg canvas whatever the backend."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained" if constrained_layout else None)
    return fig, fig.subplots(nrows, ncols, squeeze=squeeze)


def get_cmap(name: str):
    """A registered colour map by name (``pyplot.get_cmap``)."""
    import matplotlib

    return matplotlib.colormaps[name]
