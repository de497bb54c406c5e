"""`calib refine` against the simulator's exact truth, and the GT it buys back.

Each case simulates a recording with real-world errors switched on (cameras
stamped late or early, the Mid-360 IMU's noise and bias, range noise that grows
with range), gives `refine` a rig that is wrong the way real ones are (no
clock offsets, the top LiDAR and its IMU turned by 1 deg), and prints:

1. what refine recovered against the truth (offset per camera, rotation per
   LiDAR), with its stated uncertainty and whether it was observable;
2. sparse GT from the exact rig, the given (wrong) rig and the refined rig:
   range median and outliers against truth, and density.

Writes out/bench/refine.csv and out/bench/refine.png (GT error per rig and case).
The bags are cached in out/bench/refine/ (delete it to simulate afresh).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.rig import Rig, with_timeshifts, write_rig
from calibration.types import F64
from ingest.train.pipeline import IngestConfig, ingest
from ingest.train.refine import refine
from sensorbox.sim.run import SimConfig, simulate, with_mid360_imu_noise
from sensorbox.sim.score import score_dataset
from sensorbox.sim.truth import Truth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line, markdown_table

TURN = Rotation.from_rotvec(np.radians(1.0) * np.array([0.6, -0.48, 0.64])).as_matrix()
CASES = {
    "walk outdoor": dict(scene="outdoor", trajectory="walk", seed=2),
    "walk indoor": dict(scene="indoor", trajectory="walk", seed=5),
    "static room": dict(scene="indoor", trajectory="static", seed=1),
}
OFFSETS_NS = (23_000_000, -14_000_000)  # upper, lower: header stamp minus true exposure


def _turned(T: F64) -> F64:
    out = T.copy()
    out[:3, :3] = TURN @ T[:3, :3]
    return out


def wrong_rig(exact: Rig) -> Rig:
    """The exact rig without its clock offsets and with lidar_top and imu_top turned by 1 deg."""
    plain = with_timeshifts(exact, {c.name: 0.0 for c in exact.cameras})
    imu = replace(plain.imus[0], T_cam0_imu=_turned(plain.imus[0].T_cam0_imu))
    lidar = replace(plain.lidars[0], T_cam0_lidar=_turned(plain.lidars[0].T_cam0_lidar))
    return replace(plain, imus=(imu, *plain.imus[1:]), lidars=(lidar, *plain.lidars[1:]))


def _angle_deg(Ra: F64, Rb: F64) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(Ra @ Rb.T).as_rotvec())))


def _gt(bag: Path, rig: Rig, out: Path, truth: Truth, every: int) -> tuple[float, float, float]:
    """Sparse GT with `rig`: (median |range error| mm, outliers %, density % of the fisheye)."""
    rig_file = out.with_suffix(".rig") / "rig.yaml"
    rig_file.parent.mkdir(parents=True, exist_ok=True)
    write_rig(replace(rig, camchain=None), rig_file)
    if not (out / "dataset.yaml").exists():
        ingest([bag], IngestConfig(rig=rig_file, out=out, workers=2, every=every))
    scores = score_dataset(out, truth)
    px = np.array([s.depth_pixels for s in scores], float)
    med = np.array([s.depth_median_abs_m for s in scores]) * 1e3
    outl = np.array([s.depth_outlier_rate for s in scores])
    model = truth.rig.upper.model
    return (float(np.median(med)), float((outl * px).sum() / px.sum() * 100),
            float(px.mean() / (model.width * model.height) * 100))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=8.0, help="length of each simulated recording")
    parser.add_argument("--scale", type=float, default=1.0, help="image scale (1.0 = 1920x1200)")
    parser.add_argument("--every", type=int, default=6, help="ingest every n-th frame for the GT rows")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated: " + ", ".join(CASES))
    args = parser.parse_args()
    work = OUT_DIR / "refine" / f"{args.seconds:g}s_x{args.scale:g}"
    work.mkdir(parents=True, exist_ok=True)
    print(machine_line())
    rec_rows, gt_rows, csv_rows = [], [], []
    for name in args.cases.split(","):
        bag = work / name.replace(" ", "_")
        if not (bag.with_name(bag.name + ".truth") / "sim.yaml").exists():
            cfg = SimConfig(**CASES[name], duration_s=args.seconds, scale=args.scale,  # type: ignore[arg-type]
                            camera_offset_ns=OFFSETS_NS, range_noise_model="mid360")  # fmt: skip
            t0 = time.perf_counter()
            simulate(with_mid360_imu_noise(cfg), bag)
            print(f"{name}: simulated {args.seconds:g} s in {time.perf_counter() - t0:.0f} s", flush=True)
        truth = Truth.load(bag)
        given = wrong_rig(truth.rig)
        t0 = time.perf_counter()
        found = refine([bag], given)
        seconds = time.perf_counter() - t0
        for cam, true_ns in zip(found.cameras, OFFSETS_NS, strict=True):
            e = cam.estimate
            err = f"{abs(e.timeshift_ms + true_ns / 1e6):.3f}" if e.observable else "-"
            rec_rows.append([f"{name}: {cam.camera} offset [ms]", f"{-true_ns / 1e6:+.3f}",
                             f"{e.timeshift_ms:+.3f}" if e.observable else "not observable", err,
                             f"{e.sigma_ms:.3f}", f"{seconds:.0f}"])  # fmt: skip
        for imu in found.imus:
            true_R = truth.rig.lidar(imu.lidar or "").T_cam0_lidar[:3, :3]
            given_R = given.lidar(imu.lidar or "").T_cam0_lidar[:3, :3]
            refined_R = found.rig.lidar(imu.lidar or "").T_cam0_lidar[:3, :3]
            r = imu.rotation
            after = _angle_deg(refined_R, true_R)
            rec_rows.append([
                f"{name}: {imu.lidar} rotation error [deg]", f"{_angle_deg(given_R, true_R):.3f}",
                f"{after:.3f}" if r.observable else "not observable (rig's kept)", f"{after:.3f}",
                f"{r.sigma_deg:.3f}", f"{seconds:.0f}",
            ])  # fmt: skip
        for label, rig in (("exact rig", truth.rig), ("given rig", given), ("refined rig", found.rig)):
            med, outl, dens = _gt(bag, rig, work / f"{bag.name}_{label.split()[0]}", truth, args.every)
            gt_rows.append([f"{name}: {label}", f"{med:.2f}", f"{outl:.2f}", f"{dens:.2f}"])
            csv_rows.append(
                {"case": name, "rig": label, "median_mm": med, "outliers_pct": outl, "density_pct": dens}
            )
    print(f"\n{args.seconds:g} s recordings at {args.scale:g} x 1920x1200, cameras stamped "
          f"{OFFSETS_NS[0] / 1e6:+g} / {OFFSETS_NS[1] / 1e6:+g} ms, lidar_top and imu_top turned 1 deg, "
          "Mid-360 IMU noise and bias, mid360 range noise:\n")  # fmt: skip
    markdown_table(["what", "truth (given error)", "refined", "error", "1-sigma", "refine s"], rec_rows)
    print()
    markdown_table(["sparse GT", "range median [mm]", "outliers [%]", "density [%]"], gt_rows)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    with (OUT_DIR / "refine.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(csv_rows[0]))
        writer.writeheader()
        writer.writerows(csv_rows)
    _chart(csv_rows, OUT_DIR / "refine.png", args)
    print(f"\nchart: {OUT_DIR / 'refine.png'}; table: {OUT_DIR / 'refine.csv'}")


def _chart(rows: list[dict[str, Any]], path: Path, args: argparse.Namespace) -> None:
    cases = list(dict.fromkeys(str(r["case"]) for r in rows))
    rigs = ("exact rig", "given rig", "refined rig")
    colors = ("tab:green", "tab:red", "tab:blue")
    fig, ax = plt.subplots(figsize=(7, 3.8))
    width = 0.27
    for k, (rig, color) in enumerate(zip(rigs, colors, strict=True)):
        values = [
            float(next(r["median_mm"] for r in rows if r["case"] == c and r["rig"] == rig)) for c in cases
        ]
        xs = np.arange(len(cases)) + (k - 1) * width
        ax.bar(xs, values, width, color=color, label=rig)
        for x, v in zip(xs, values, strict=True):
            ax.text(x, v, f"{v:.1f}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(np.arange(len(cases)), cases)
    ax.set_ylabel("sparse GT range error, median [mm]")
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_title(
        f"calib refine: GT before and after ({args.seconds:g} s, {args.scale:g} x 1920x1200)", fontsize=9
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
