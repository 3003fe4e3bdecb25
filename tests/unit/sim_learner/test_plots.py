"""sim_learner/plots.py: the paper's command-domain drawings, shared with ``scmbridge pairs plot``.

``scmbridge pairs plot`` writes this figure end to end in tests/integration/test_pairs_cli.py; here what the helpers
and the figure promise: one colour per pair on both domains, the box outline, the three panels with their titles and
frames (widened to whatever is drawn outside the bounds), the mapping region of known pair ids only, the commands."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.patches import Polygon, Rectangle

from sim_learner.plots import command_domains_figure, draw_box, draw_pairs, pair_colors
from tests.boxes import LB, TB
from transfer.domain import Bounds


def test_pair_colors_are_one_per_pair_from_viridis() -> None:
    c = pair_colors(5)
    assert c.shape == (5, 4) and len({tuple(x) for x in c}) == 5
    np.testing.assert_allclose(c[0], plt.cm.viridis(0.0))
    np.testing.assert_allclose(c[-1], plt.cm.viridis(1.0))
    assert pair_colors(0).shape == (0, 4) and pair_colors(1).shape == (1, 4)


def test_draw_box_outlines_the_box_and_draw_pairs_matches_colours_across_domains() -> None:
    fig, (a, b) = plt.subplots(1, 2)
    draw_box(a, LB, ec="red", label="limits")
    (r,) = [p for p in a.patches if isinstance(p, Rectangle)]
    assert (r.get_x(), r.get_y(), r.get_width(), r.get_height()) == pytest.approx(
        (LB.v[0], LB.w[0], LB.span[0], LB.span[1]))
    assert not r.get_fill() and r.get_label() == "limits"
    T, L = np.array([[0.1, 0.0], [0.3, 0.2], [0.5, -0.3]]), np.array([[0.06, 0.0], [0.15, 0.1], [0.25, -0.1]])
    draw_pairs(a, b, T, L)
    (st,), (sl,) = a.collections, b.collections
    np.testing.assert_allclose(st.get_offsets(), T)
    np.testing.assert_allclose(sl.get_offsets(), L)
    np.testing.assert_allclose(st.get_facecolors(), sl.get_facecolors())  # pair k: one colour on both sides
    np.testing.assert_allclose(st.get_facecolors(), pair_colors(3))


L0 = LB.denormalise(np.array([[0.05, 0.05], [0.15, 0.15], [0.25, 0.25], [0.55, 0.45]]))  # cells 0, 12, 24, 60
T0 = L0 * np.array([1.3, 1.1])


def _figure(**kw):
    args = {"ids": [0, 12, 24, 60], "teacher": T0, "learner": L0, "teacher_bounds": TB, "learner_bounds": LB}
    args.update(kw)
    return command_domains_figure(**args), T0, L0


def test_the_figure_has_three_panels_framed_on_their_bounds() -> None:
    fig, T, L = _figure(title="robot r1")
    ax_t, ax_z, ax_l = fig.axes
    assert [a.get_title() for a in fig.axes] == ["(a) teacher command domain",
                                                 "(a') teacher command domain, the learned limits",
                                                 "(b) learner command domain"]
    assert fig.texts[0].get_text() == "robot r1"
    lo, hi = ax_t.get_xlim()
    assert lo < TB.v[0] < TB.v[1] < hi and lo == pytest.approx(TB.v[0] - 0.05 * TB.span[0])
    lo, hi = ax_l.get_ylim()
    assert lo == pytest.approx(LB.w[0] - 0.05 * LB.span[1]) and hi == pytest.approx(LB.w[1] + 0.05 * LB.span[1])
    assert ax_l.get_xlabel() == "v (m/s)" and ax_l.get_ylabel() == "omega (rad/s)"


def test_points_outside_the_bounds_widen_the_frame() -> None:
    far = np.array([[0.05, 0.0], [0.1, 0.1], [0.9, 0.0], [0.2, -0.1]])  # 0.9 m/s: beyond the teacher's bounds
    fig, _, _ = _figure(teacher=far)
    assert fig.axes[0].get_xlim()[1] > 0.9


def test_only_known_ids_of_the_region_are_drawn_and_the_commands_are_marked() -> None:
    fig, T, L = _figure(region=[12, 24, 60, 999], teacher_cmd=[0.2, 0.1], learner_cmd=[0.15, 0.05], grid=(11, 11),
                        limits_box=Bounds((0.05, 0.4), (-0.2, 0.3)), hull=T0[[0, 2, 3]], triangles=[[0, 1, 3]])
    ax_t, ax_z, ax_l = fig.axes
    regions = [p for p in ax_l.patches if isinstance(p, Polygon)]
    assert len(regions) == 1 and regions[0].get_label() == "mapping region [12, 24, 60]"  # 999 is not a pair
    np.testing.assert_allclose(regions[0].get_xy()[:3], L[[1, 2, 3]])
    for ax in (ax_z, ax_l):  # the ids are named on the zoomed teacher panel and on the learner's, not on (a)
        assert [t.get_text() for t in ax.texts] == ["12", "24", "60"]
    assert len(ax_t.texts) == 0
    crosses = [c for c in ax_l.collections if c.get_label() == "learner command"]
    assert len(crosses) == 1 and crosses[0].get_offsets().tolist() == [[0.15, 0.05]]
    hulls = [p for p in ax_t.patches if isinstance(p, Polygon) and p.get_label() == "learned limits (hull)"]
    assert len(hulls) == 1
    shaded = [p for p in ax_l.patches if isinstance(p, Rectangle) and p.get_facecolor()[3] == pytest.approx(0.08)]
    assert len(shaded) == 4  # the configured cells of the four pairs
