"""Fixed figure margins in inches, instead of a layout engine.

Matplotlib's constrained layout (and ``tight_layout``) measures every text
of a figure on each draw, which cost more than half the time of writing the
registration's figures; the figures here have known contents, so their
margins are set once, in inches, and converted to the fractions of the
figure that :meth:`matplotlib.figure.Figure.subplots_adjust` takes.
"""

from __future__ import annotations

__all__ = ["PNG_OPTIONS", "fixed_margins", "subplots"]

#: zlib level of the pictures' and figures' PNGs (Pillow's default 6): level 3 writes the model's two
#: pictures in 0.10 s instead of 0.22 s, the files within 3 % of the size.
PNG_OPTIONS = {"compress_level": 3}


def subplots(fig, *args, **kwargs):
    """``fig.subplots(*args, **kwargs)`` with each title fixed at the top of its axes.

    By default matplotlib measures every axis's tick labels on each draw to lift
    a title above labels on top, which no figure here has (about an eighth
    of the time of writing the registration's figures).
    """
    import numpy as np

    axes = fig.subplots(*args, **kwargs)
    for ax in np.ravel(axes):  # through each axes, not rcParams: two pictures are drawn at once on two threads
        ax.set_title("", y=1.0)  # an explicit y: not lifted above tick labels, nor measured for it
    return axes


def fixed_margins(fig, *, left_in: float, right_in: float, bottom_in: float, top_in: float,
                  wspace_in: float = 0.0, hspace_in: float = 0.0) -> None:
    """Place the figure's grid of subplots with margins and gaps given in inches.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        With its subplots made (``fig.subplots``); the grid's shape is read
        from the first axes' grid spec.
    left_in, right_in, bottom_in, top_in : float
        Room (inches) between the figure's edges and the outer subplots, for
        tick labels, axis labels, titles, a suptitle or a figure legend.
    wspace_in, hspace_in : float
        Gap (inches) between neighbouring columns and rows of subplots.

    Raises
    ------
    ValueError
        If the margins and gaps leave no room for the subplots.
    """
    width_in, height_in = fig.get_size_inches()
    nrows, ncols = 1, 1
    for ax in fig.axes:
        spec = ax.get_subplotspec()
        if spec is not None:
            nrows, ncols = spec.get_gridspec().get_geometry()
            break
    ax_w = (width_in - left_in - right_in - (ncols - 1) * wspace_in) / ncols
    ax_h = (height_in - bottom_in - top_in - (nrows - 1) * hspace_in) / nrows
    if ax_w <= 0 or ax_h <= 0:
        raise ValueError(f"margins leave no room for the {nrows} x {ncols} subplots of a "
                         f"{width_in:g} x {height_in:g} in figure")
    fig.subplots_adjust(left=left_in / width_in, right=1.0 - right_in / width_in,
                        bottom=bottom_in / height_in, top=1.0 - top_in / height_in,
                        wspace=wspace_in / ax_w, hspace=hspace_in / ax_h)
