"""Dense vs sparse ground truth at full resolution: `sensorbox.analysis.dense_study` as a table and a chart.

Prints a markdown row per scene and method as it is measured, then the
trajectory's error over the walk, and writes out/bench/dense.png (density vs
range error with each scene's Pareto front).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line

from sensorbox.analysis.dense_study import dense_chart, format_row, run_dense_study, table_header


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=3, help="samples per scene and method")
    ap.add_argument("--walk-s", type=float, default=20.0, help="length of the walk (trajectory error)")
    ap.add_argument("--out", type=Path, default=OUT_DIR / "dense")
    args = ap.parse_args()
    print(machine_line())
    print(table_header())
    result = run_dense_study(
        args.out, args.samples, args.walk_s, lambda *row: print(format_row(*row), flush=True)
    )
    print(result.trajectory_line())
    OUT_DIR.mkdir(parents=True, exist_ok=True)  # --out may lie elsewhere
    dense_chart(result.rows, OUT_DIR / "dense.png")
    print(f"chart: {OUT_DIR / 'dense.png'}")


if __name__ == "__main__":
    main()
