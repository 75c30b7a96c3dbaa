"""The operating-point report: the heat maps' cuts hold the search's own scores, the table its best points."""

import numpy as np
import pytest

from deepword.operating_point.report import (
    operating_point_markdown,
    plot_operating_point,
    side_surface,
    threshold_surface,
)
from deepword.operating_point.search import OperatingPoint


def seen_grid() -> dict[OperatingPoint, float]:
    """A 3 x 2 threshold grid times a 1 x 2 side grid, each point's score distinct (thresholds and sides encoded)."""
    return {OperatingPoint((tv, tw), (0.0, sw)): 10 * tv + tw + sw / 100
            for tv in (0.1, 0.3, 0.5) for tw in (0.2, 0.4) for sw in (0.0, 7.0)}


def test_the_threshold_cut_holds_each_points_score_at_the_fixed_sides():
    seen = seen_grid()
    xs, ys, grid = threshold_surface(seen, (0.0, 7.0))
    assert xs == [0.1, 0.3, 0.5] and ys == [0.2, 0.4] and grid.shape == (2, 3)
    for i, tw in enumerate(ys):
        for j, tv in enumerate(xs):
            assert grid[i, j] == seen[OperatingPoint((tv, tw), (0.0, 7.0))]


def test_the_side_cut_holds_each_points_score_at_the_fixed_thresholds_and_nan_where_unscored():
    seen = seen_grid()
    seen.update({OperatingPoint((0.3, 0.4), (20.0, 0.0)): 1.0, OperatingPoint((0.3, 0.4), (20.0, 7.0)): 2.0})
    del seen[OperatingPoint((0.3, 0.4), (0.0, 0.0))]
    xs, ys, grid = side_surface(seen, (0.3, 0.4))
    assert xs == [0.0, 20.0] and ys == [0.0, 7.0]
    assert np.isnan(grid[0, 0]) and grid[1, 0] == seen[OperatingPoint((0.3, 0.4), (0.0, 7.0))]
    assert grid[0, 1] == 1.0 and grid[1, 1] == 2.0
    with pytest.raises(ValueError, match="no two-class points"):
        side_surface(seen, (0.9, 0.9))


def test_the_table_ranks_the_best_points_and_names_the_chosen_one():
    seen = seen_grid()
    chosen = max(seen, key=seen.get)
    text = operating_point_markdown(seen, chosen, ["vehicle", "wheel"], at_score_threshold=12.5,
                                    method="deepword_then_logic", alone=3.25, top=3)
    assert "| **chosen** | 0.50 | 0.40 | 0 | 7 | **5.47** |" in text
    assert "| the relation model alone, same point | 0.50 | 0.40 | 0 | 7 | 3.25 |" in text
    assert "| every detection kept | – | – | – | – | 12.50 |" in text
    ranks = [line for line in text.splitlines() if line[:4] in ("| 1 ", "| 2 ", "| 3 ", "| 4 ")]
    assert [r.split("|")[-2].strip() for r in ranks] == ["5.47", "5.40", "5.27"]


def test_the_figure_is_written_for_two_classes_and_refused_for_others(tmp_path):
    seen = seen_grid()
    chosen = OperatingPoint((0.3, 0.2), (0.0, 7.0))
    plot_operating_point(seen, chosen, ["vehicle", "wheel"], tmp_path / "op.png", "deepword")
    assert (tmp_path / "op.png").stat().st_size > 10_000
    with pytest.raises(ValueError, match="two classes"):
        plot_operating_point(seen, chosen, ["vehicle"], tmp_path / "one.png")
