"""`calib refine` against the simulator's exact truth, and the GT it buys back; the per-sample scores.

Each case simulates a recording with real-world errors switched on (cameras
stamped late or early, the Mid-360 IMU's noise and bias, range noise that grows
with range; one case with mixed returns at depth edges), gives `refine` a rig
that is wrong the way real ones are (no clock offsets, lidar_top turned by 1 deg
and moved by 30 mm, lidar_bottom by 0.5 deg and 20 mm, each with its IMU), and
prints:

1. what refine recovered against the truth (offset per camera, rotation and
   translation per LiDAR), with its stated uncertainty and whether it was
   observable; with `--alone`, also from each kind of error alone (the clock
   offsets with exact LiDAR poses, the LiDAR poses with exact clocks);
2. sparse GT from the exact rig, the given (wrong) rig and the refined rig:
   range median and outliers against truth, and density;
3. with `--scores`: the truth-free alignment score of every sample (the median
   angle its LiDAR points sit off cam0's image, `ingest.train.gt.align`) for the
   exact rig and for one error at a time (both cameras 5 ms late, lidar_top
   turned 0.25 deg), against each sample's true GT error: ROC AUC of the score
   between exact and wrong samples, and whether ingest's warning fired.

Writes out/bench/refine.csv, refine.png (GT error per rig and case) and, with
`--scores`, refine_scores.png (score against true GT error).
The bags are cached in out/bench/refine/ (delete it to simulate afresh).
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import textwrap
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
from ingest.dataset.meta import read_meta
from ingest.train.run.pipeline import ingest, refine_rig
from ingest.train.run.refine import Refinement
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.config import SimConfig, with_mid360_imu_noise
from sensorbox.sim.run import simulate
from sensorbox.sim.score import score_dataset
from sensorbox.sim.truth import Truth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line, markdown_table

CASES = {
    "walk outdoor": dict(scene="outdoor", trajectory="walk", seed=2),
    "walk indoor": dict(scene="indoor", trajectory="walk", seed=5),
    "static room": dict(scene="indoor", trajectory="static", seed=1),
    "walk outdoor mixed returns": dict(scene="outdoor", trajectory="walk", seed=2, mixed_returns=True),
}
OFFSETS_NS = (23_000_000, -14_000_000)  # upper, lower: header stamp minus true exposure
ERRORS = (  # per LiDAR (and its IMU): rotation vector (deg), translation (m), in cam0
    (np.array([0.6, -0.48, 0.64]), np.array([0.02, -0.015, 0.0158])),  # 1 deg, 29.6 mm
    (np.array([-0.2, 0.3, 0.3464]), np.array([-0.01, 0.012, -0.0126])),  # 0.5 deg, 20.0 mm
)


def _moved(T: F64, rotvec_deg: F64, shift_m: F64) -> F64:
    """`T` (cam0 <- sensor) turned about cam0's origin by `rotvec_deg` and moved by `shift_m`."""
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix() @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + shift_m
    return out


def wrong_rig(exact: Rig) -> Rig:
    """The exact rig without its clock offsets and with each LiDAR and its IMU moved by `ERRORS`."""
    plain = with_timeshifts(exact, {c.name: 0.0 for c in exact.cameras})
    lidars = tuple(replace(lidar, T_cam0_lidar=_moved(lidar.T_cam0_lidar, *err))
                   for lidar, err in zip(plain.lidars, ERRORS, strict=False))  # fmt: skip
    imus = tuple(replace(imu, T_cam0_imu=_moved(imu.T_cam0_imu, *err))
                 for imu, err in zip(plain.imus, ERRORS, strict=False))  # fmt: skip
    return replace(plain, lidars=lidars, imus=imus)


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
    parser.add_argument("--scores", action="store_true", help="also the per-sample score study (part 3)")
    parser.add_argument(
        "--alone",
        action="store_true",
        help="also refine from each kind of error alone (clock offsets; LiDAR poses)",
    )
    parser.add_argument("--tag", default="", help="suffix of the output files (refine<TAG>.csv, ...)")
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
        found, rows = _recover(name, truth, given, bag)
        rec_rows += rows
        for what, alone in _alone_rigs(truth.rig, given) if args.alone else ():
            rec_rows += _recover(f"{name} ({what})", truth, alone, bag)[1]
        for label, rig in (("exact rig", truth.rig), ("given rig", given), ("refined rig", found.rig)):
            med, outl, dens = _gt(bag, rig, work / f"{bag.name}_{label.split()[0]}", truth, args.every)
            gt_rows.append([f"{name}: {label}", f"{med:.2f}", f"{outl:.2f}", f"{dens:.2f}"])
            csv_rows.append(
                {"case": name, "rig": label, "median_mm": med, "outliers_pct": outl, "density_pct": dens}
            )
    print(f"\n{args.seconds:g} s recordings at {args.scale:g} x 1920x1200, cameras stamped "
          f"{OFFSETS_NS[0] / 1e6:+g} / {OFFSETS_NS[1] / 1e6:+g} ms, lidar_top (and its IMU) off by 1 deg "
          "and 30 mm, lidar_bottom by 0.5 deg and 20 mm, Mid-360 IMU noise and bias, mid360 range "
          "noise:\n")  # fmt: skip
    header = ["what", "truth (given error)", "refined", "error", "1-sigma", "refine s (CPU s)"]
    markdown_table(header, rec_rows)
    print()
    markdown_table(["sparse GT", "range median [mm]", "outliers [%]", "density [%]"], gt_rows)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    with (OUT_DIR / f"refine{args.tag}.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(csv_rows[0]))
        writer.writeheader()
        writer.writerows(csv_rows)
    _chart(csv_rows, OUT_DIR / f"refine{args.tag}.png", args)
    print(f"\nchart: {OUT_DIR / f'refine{args.tag}.png'}; table: {OUT_DIR / f'refine{args.tag}.csv'}")
    if args.scores:
        _score_study(args, work)


def _alone_rigs(exact: Rig, given: Rig) -> tuple[tuple[str, Rig], ...]:
    """The given rig's errors one kind at a time: the clock offsets alone (the LiDARs exact), the
    LiDAR poses alone (the clock offsets exact)."""
    offsets = with_timeshifts(exact, {c.name: c.timeshift_cam_imu or 0.0 for c in given.cameras})
    poses = with_timeshifts(given, {c.name: c.timeshift_cam_imu or 0.0 for c in exact.cameras})
    return (("clock offsets alone", offsets), ("LiDAR poses alone", poses))


def _recover(name: str, truth: Truth, given: Rig, bag: Path) -> tuple[Refinement, list[list[str]]]:
    """`refine_rig` of `bag` from the `given` rig, and the table's rows: what it recovered against the
    truth, with its stated uncertainty, its wall and CPU time."""
    t0, cpu0 = time.perf_counter(), os.times()
    found = refine_rig([bag], given)
    seconds, cpu1 = time.perf_counter() - t0, os.times()
    cpu_s = sum(cpu1[:4]) - sum(cpu0[:4])  # this process and its workers (user + system)
    took = f"{seconds:.0f} ({cpu_s:.0f} CPU)"
    rows = []
    for cam, true_ns in zip(found.cameras, OFFSETS_NS, strict=True):
        e = cam.estimate
        err = f"{abs(e.timeshift_ms + true_ns / 1e6):.3f}" if e.observable else "-"
        rows.append([f"{name}: {cam.camera} offset [ms]", f"{-true_ns / 1e6:+.3f}",
                     f"{e.timeshift_ms:+.3f}" if e.observable else "not observable", err,
                     f"{e.sigma_ms:.3f}", took])  # fmt: skip
    for lidar in truth.rig.lidars:
        T_true = lidar.T_cam0_lidar
        T_given, T_found = given.lidar(lidar.name).T_cam0_lidar, found.rig.lidar(lidar.name).T_cam0_lidar
        mine = next((r for r in found.lidars if r.lidar == lidar.name), None)
        applied = mine is not None and mine.applied
        angles = [_angle_deg(T[:3, :3], T_true[:3, :3]) for T in (T_given, T_found)]
        shifts = [float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]) * 1e3) for T in (T_given, T_found)]
        sigmas = (None, None) if mine is None else (mine.sigma_rotation_deg, mine.sigma_translation_mm)
        for what, (before, after), sigma in zip(
            ("rotation error [deg]", "translation error [mm]"), (angles, shifts), sigmas, strict=True
        ):
            rows.append([
                f"{name}: {lidar.name} {what}", f"{before:.3f}",
                f"{after:.3f}" if applied else "not applied (rig's kept)", f"{after:.3f}",
                "-" if sigma is None else f"{sigma:.3f}", took,
            ])  # fmt: skip
    print(f"{name}: refine took {seconds:.0f} s ({cpu_s:.0f} CPU s)", *[" | ".join(r[:5]) for r in rows],
          f"stereo check: {found.stereo_alignment}", f"clock check: {found.image_clock_ms}",
          sep="\n  ", flush=True)  # fmt: skip
    return found, rows


SCORE_VARIANTS = ("exact rig", "cameras 5 ms late", "lidar_top turned 0.25 deg")


def _variant(exact: Rig, variant: str) -> Rig:
    """The exact rig with one error of `SCORE_VARIANTS`."""
    if variant == "cameras 5 ms late":
        return with_timeshifts(exact, {c.name: (c.timeshift_cam_imu or 0.0) + 0.005 for c in exact.cameras})
    if variant == "lidar_top turned 0.25 deg":
        T = _moved(
            exact.lidars[0].T_cam0_lidar, ERRORS[0][0] / np.linalg.norm(ERRORS[0][0]) * 0.25, np.zeros(3)
        )
        return replace(exact, lidars=(replace(exact.lidars[0], T_cam0_lidar=T), *exact.lidars[1:]))
    return exact


def _auc(negatives: list[float], positives: list[float]) -> float:
    """ROC AUC: the chance that a positive's score exceeds a negative's (ties count half)."""
    neg, pos = np.asarray(negatives), np.asarray(positives)
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(greater / (len(pos) * len(neg)))


def _score_study(args: argparse.Namespace, work: Path) -> None:
    """Part 3: per-sample scores for the exact rig and one error at a time, against the true GT error."""
    rows, points = [], []
    for name in args.cases.split(","):
        bag = work / name.replace(" ", "_")
        truth = Truth.load(bag)
        by_variant: dict[str, list[float]] = {}
        for variant in SCORE_VARIANTS:
            out = work / f"{bag.name}_scores_{'_'.join(variant.split()[:2])}"
            rig_file = out.with_suffix(".rig") / "rig.yaml"
            rig_file.parent.mkdir(parents=True, exist_ok=True)
            write_rig(replace(_variant(truth.rig, variant), camchain=None), rig_file)
            warned = ""
            if not (out / "dataset.yaml").exists():
                summary = ingest([bag], IngestConfig(rig=rig_file, out=out, workers=2, every=args.every))
                warned = "yes" if any("calib refine" in w for w in summary.warnings) else "no"
            truth_scores = {s.sid: s for s in score_dataset(out, truth)}
            scores = []
            for sid, true in truth_scores.items():
                meta = read_meta(out, sid)
                score = max((a.shift_deg for a in meta.alignment.values()), default=float("nan"))
                scores.append(score)
                points.append((name, variant, score, true.depth_median_abs_m * 1e3))
            by_variant[variant] = scores
            auc = (
                "-" if variant == SCORE_VARIANTS[0] else f"{_auc(by_variant[SCORE_VARIANTS[0]], scores):.3f}"
            )
            rows.append([f"{name}: {variant}", f"{np.median(scores):.3f}", f"{np.max(scores):.3f}", auc,
                         warned or "(cached)"])  # fmt: skip
    print()
    markdown_table(["samples", "score median [deg]", "score max [deg]", "ROC AUC vs exact", "warned"], rows)
    _score_chart(points, OUT_DIR / f"refine_scores{args.tag}.png", args)
    print(f"\nchart: {OUT_DIR / f'refine_scores{args.tag}.png'}")


def _score_chart(points: list[tuple[str, str, float, float]], path: Path, args: argparse.Namespace) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    colors = dict(zip(SCORE_VARIANTS, ("tab:green", "tab:orange", "tab:red"), strict=True))
    markers = dict(zip(CASES, "os^D", strict=True))
    for case, variant, score, err in points:
        ax.scatter(score, err, s=12, color=colors[variant], marker=markers[case], alpha=0.7)
    for variant, color in colors.items():
        ax.scatter([], [], color=color, label=variant, s=12)
    for case, marker in markers.items():
        if any(p[0] == case for p in points):
            ax.scatter([], [], color="grey", marker=marker, label=case, s=12)
    ax.set_xlabel("alignment score: LiDAR points off cam0's image, median [deg] (no truth)")
    ax.set_ylabel("true sparse GT range error, median [mm]")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(f"per-sample score against true GT error ({args.seconds:g} s, {args.scale:g} x 1920x1200)",
                 fontsize=9)  # fmt: skip
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


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
    ax.set_xticks(np.arange(len(cases)), [textwrap.fill(c, 14) for c in cases])
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
