"""hrcore.figlayout: subplots placed by margins and gaps given in inches."""

import numpy as np
import pytest

from hrcore.figlayout import fixed_margins


def _boxes_in(fig):
    w, h = fig.get_size_inches()
    return [np.array(ax.get_position().bounds) * [w, h, w, h] for ax in fig.axes]


def test_margins_and_gaps_in_inches():
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10.0, 6.0), dpi=100)
    fig.subplots(2, 3)
    fixed_margins(fig, left_in=0.7, right_in=0.2, bottom_in=0.5, top_in=0.6, wspace_in=0.8, hspace_in=0.4)
    assert fig.get_layout_engine() is None
    boxes = _boxes_in(fig)  # x0, y0, width, height (inches), row by row from the top
    x0 = sorted({round(b[0], 9) for b in boxes})
    y0 = sorted({round(b[1], 9) for b in boxes})
    width, height = boxes[0][2], boxes[0][3]
    assert x0[0] == pytest.approx(0.7) and y0[0] == pytest.approx(0.5)
    assert x0[2] + width == pytest.approx(10.0 - 0.2)
    assert y0[1] + height == pytest.approx(6.0 - 0.6)
    assert x0[1] - (x0[0] + width) == pytest.approx(0.8)
    assert y0[1] - (y0[0] + height) == pytest.approx(0.4)


def test_one_axes_and_no_room():
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.0, 3.0))
    fig.subplots()
    fixed_margins(fig, left_in=1.0, right_in=0.5, bottom_in=0.5, top_in=0.5)
    (box,) = _boxes_in(fig)
    assert box == pytest.approx([1.0, 0.5, 2.5, 2.0])
    with pytest.raises(ValueError, match="no room"):
        fixed_margins(fig, left_in=2.0, right_in=2.0, bottom_in=0.5, top_in=0.5)
