"""The dense-GT study's table and chart (the study itself runs in bench/, ~30 min)."""

import cv2

from sensorbox.analysis.dense_study import METHODS, dense_chart, format_row, pareto_front


def test_pareto_front_keeps_only_undominated_points():
    pts = [(1.0, 0.3), (10.0, 0.3), (30.0, 0.5), (20.0, 0.6), (50.0, 2.0)]
    assert pareto_front(pts) == [(10.0, 0.3), (30.0, 0.5), (50.0, 2.0)]


def test_row_and_chart(tmp_path):
    r = {"density": 0.335, "median_mm": 0.27, "outliers": 0.002, "disp_median_px": 0.003, "disp_over_1px": 0.0009,
         "trail": 0.0, "s_per_sample": 16.6, "disp_per_depth": 1.084}  # fmt: skip
    assert format_row("static room", "odometry +-500 ms", r) == (
        "| static room | odometry +-500 ms | 33.5 % | 0.27 | 0.20 % | 0.003 | 0.09 % | 1.08 | 0.000 % | 16.6 |"
    )
    rows = {
        scene: {
            m.label: {**r, "density": 0.01 * m.window_ms / 10, "median_mm": 0.2 + m.window_ms / 1000}
            for m in METHODS
        }
        for scene in ("static room", "outdoor walk")
    }
    dense_chart(rows, tmp_path / "dense.png")
    img = cv2.imread(str(tmp_path / "dense.png"))
    assert img is not None and img.shape[1] > 2 * img.shape[0] * 0.8
