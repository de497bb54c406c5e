"""Speed vs accuracy of the ingest pipeline's alternatives, and equirect vs cubemap stereo (README charts).

Runs `sensorbox bench` as a library call on two simulated, noise-free bags with
exact truth (indoor static room, outdoor walk; scale 0.5 = 960 x 600 fisheyes,
0.5 s each), every alternative of `sensorbox.analysis.tradeoff.ALTERNATIVES`, three timing
rounds (each sample's time is the median of its rounds; rounds interleave the
alternatives so a busy spell on a shared machine hits them alike). Prints the
markdown tables and writes bench_tradeoff.csv/.png and bench_projection.csv/.png
into docs/ (or --out).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sensorbox.analysis.bench import default_sims, projection_table, run_bench, tradeoff_table
from sensorbox.analysis.tradeoff import ALTERNATIVES
from sensorbox.sim.run import simulate

DOCS = Path(__file__).resolve().parents[1] / "docs"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=DOCS, help="folder for the CSVs and charts")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale of the simulated rig")
    parser.add_argument("--duration", type=float, default=0.5, help="seconds per simulated bag")
    parser.add_argument("--repeats", type=int, default=3, help="timing rounds")
    args = parser.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-tradeoff-") as tmp:
        bags = [simulate(cfg, Path(tmp) / name).bag for name, cfg in default_sims(args.scale, args.duration)]
        result = run_bench(
            bags, args.out, ALTERNATIVES, Path(tmp) / "work", repeats=args.repeats,
            progress=lambda what: print(f"  {what}", file=sys.stderr, flush=True),
        )  # fmt: skip
    print(
        f"# Ingest alternatives, image scale {args.scale}, {args.duration} s per bag, {args.repeats} rounds"
    )
    print(f"(pooled over {', '.join(b.name for b in bags)}; samples/s = one worker, 1000 / median")
    print(" per-sample stage time; Pareto: on the front of speed vs median mm and/or vs outlier %)\n")
    print(tradeoff_table(result.pooled))
    for bag in bags:
        per_bag = [m for m in result.measurements if m.bag == bag.name]
        print(f"\n## {bag.name}\n")
        print(tradeoff_table(per_bag))
    print(f"\n# Stereo on equirect vs cubemap faces (SGBM, {bags[0].name}, {result.projection_source})\n")
    print(projection_table(result.projection))
    print(f"\nwritten in {time.perf_counter() - t0:.0f} s: " + ", ".join(str(p) for p in result.files))


if __name__ == "__main__":
    main()
