"""Stability maps: where each method of the pipeline stops being trustworthy (README charts).

Writes into docs/ (or --out), one chart per region of `sensorbox.analysis.stability`, and
prints a table for each:

1. stability_ds.png: the reference Double Sphere's radial/tangential resolution
   against the angle off its axis, the validity limit, the image's edges and
   corners, and the mask (radial resolution >= half the centre's) on the image.
2. stability_disparity.png: relative range error from a 0.5 px disparity error
   over latitude x range (reference rig, H_full 2048), with the pipeline's mask.
3. stability_cubemap.png: SGBM on the stereo cubemap faces of a simulated room:
   match rate and bad-1 against the distance from the face edges, plain and
   padded faces, and the seam mask's boundary.
4. stability_time_offset.png: a simulated walk (1.2 m/s, up to 60 deg/s),
   ingested once; its GT scored against the truth 0-20 ms before the frame
   stamp (camera stamps late by that much), on all GT and on the GT the
   displacement mask keeps.
5. stability_extrinsic.png: a simulated room ingested with T_cam0_lidar of both
   LiDARs rotated by 0-1 degree; all GT vs the GT the mask keeps.

Simulated bags: noise-free, image scale 0.5 (960 x 600 fisheyes).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Rectangle

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration.fisheye import DoubleSphere
from calibration.linalg3 import rotvec_to_matrix
from calibration.rig import REFERENCE_RIG, read_rig, write_rig
from calibration.types import F64
from ingest.dataset.layout import DEPTH_SCALE, read_png_u16
from ingest.dataset.meta import SampleMeta, read_meta
from ingest.train.gt.groundtruth import GtParams, px_per_rad
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.analysis.projection import compare_projections, num_disparities_for
from sensorbox.analysis.stability import (
    disparity_range_error,
    displacement_mask,
    ds_radial_resolution,
    ds_stability_mask,
    ds_stable_angle_rad,
    ds_validity_limit_rad,
    extrinsic_displacement_px,
    extrinsic_range_error_m,
    time_offset_displacement_px,
    time_offset_range_error_m,
)
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.truth import Truth

DOCS = Path(__file__).resolve().parents[1] / "docs"
DS_MIN_RATIO = 0.5
DISP_ERROR_PX = 0.5
OFFSETS_MS = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0)
ANGLES_DEG = (0.0, 0.1, 0.25, 0.5, 1.0)
EXTRINSIC_AXIS = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])  # in each LiDAR's frame


def _table(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _save(fig: Any, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# -- 1. Double Sphere ---------------------------------------------------------------------


def _ds_edges_deg(model: DoubleSphere) -> dict[str, float]:
    """Largest angle off the axis (deg) on each kind of image edge."""
    edges = {
        "left/right edge": [[-0.5, model.cy], [model.width - 0.5, model.cy]],
        "top/bottom edge": [[model.cx, -0.5], [model.cx, model.height - 0.5]],
        "corners": [[-0.5, -0.5], [model.width - 0.5, model.height - 0.5]],
    }
    edge_deg = {}
    for name, px in edges.items():
        rays, ok = model.unproject(np.array(px))
        edge_deg[name] = float(np.degrees(np.arccos(rays[ok, 2])).max()) if ok.any() else math.nan
    return edge_deg


def _ds_image_circle(model: DoubleSphere, centre_px_per_rad: float) -> tuple[F64, F64, F64, F64]:
    """Over the whole image circle (beyond the sensor), every 4th pixel: (u, v, radial / centre, mask)."""
    R = (
        model.fx / math.sqrt(2 * model.alpha - 1)
        if model.alpha > 0.5
        else 1.5 * max(model.width, model.height)
    )
    us = np.arange(model.cx - R - 20, model.cx + R + 20, 4.0)
    vs = np.arange(model.cy - R - 20, model.cy + R + 20, 4.0)
    wide = np.stack(np.meshgrid(us, vs), axis=-1)
    wide_rays, wide_ok = model.unproject(wide)
    theta = np.arccos(np.nan_to_num(wide_rays[..., 2], nan=1.0))
    ratio = np.where(wide_ok, ds_radial_resolution(model, theta), np.nan) / centre_px_per_rad
    return us, vs, ratio, ds_stability_mask(model, wide, DS_MIN_RATIO).astype(float)


def ds_chart(out: Path) -> str:
    model = read_rig(REFERENCE_RIG).upper.model
    assert isinstance(model, DoubleSphere)
    limit, stable = ds_validity_limit_rad(model), ds_stable_angle_rad(model, DS_MIN_RATIO)
    theta = np.radians(np.linspace(0.0, math.degrees(limit) + 1.2, 800))
    radial = ds_radial_resolution(model, theta)
    uv, _ = model.project(np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], 1))
    with np.errstate(invalid="ignore", divide="ignore"):
        tangential = np.where(theta > 0, (uv[:, 0] - model.cx) / np.sin(theta), radial[0])
    edge_deg = _ds_edges_deg(model)
    grid = model.pixel_grid()
    _, ok = model.unproject(grid)
    mask = ds_stability_mask(model, grid, DS_MIN_RATIO)
    us, vs, ratio, wide_mask = _ds_image_circle(model, float(radial[0]))
    fig, ax = plt.subplots(1, 2, figsize=(15, 5.2), constrained_layout=True, width_ratios=[1.1, 1])
    ax[0].plot(np.degrees(theta), radial, label="radial dr/dtheta")
    ax[0].plot(np.degrees(theta), tangential, label="tangential r/sin(theta)")
    ax[0].axhline(DS_MIN_RATIO * radial[0], color="k", lw=0.8, ls=":", label=f"{DS_MIN_RATIO:g} x centre")
    ax[0].axvline(
        math.degrees(stable), color="tab:red", lw=1.5, label=f"mask: {math.degrees(stable):.1f} deg"
    )
    ax[0].axvline(
        math.degrees(limit), color="k", lw=1.5, label=f"validity limit {math.degrees(limit):.1f} deg"
    )
    for (name, deg), ls in zip(edge_deg.items(), ("--", "-.", ":"), strict=True):
        ax[0].axvline(deg, color="tab:gray", ls=ls, label=f"image {name}: {deg:.1f} deg")
    ax[0].set_xlabel("angle off the optical axis [deg]")
    ax[0].set_ylabel("resolution [px/rad]")
    ax[0].set_ylim(0, 1400)
    ax[0].legend(fontsize=8, loc="lower left")
    ax[0].set_title(f"Reference DS lens (xi {model.xi:.3f}, alpha {model.alpha:.3f}, f {model.fx:.0f} px)")
    extent = (us[0], us[-1], vs[-1], vs[0])
    shown = ax[1].imshow(ratio, vmin=0.0, vmax=1.0, cmap="viridis", extent=extent)
    ax[1].contour(us, vs, wide_mask, [0.5], colors="tab:red", linewidths=1.5)
    ax[1].add_patch(Rectangle((-0.5, -0.5), model.width, model.height, fill=False, ec="white", lw=1.5))
    ax[1].set_title(
        f"radial resolution / centre's over the whole image circle;\nwhite: the {model.width}x"
        f"{model.height} sensor; red: mask edge ({DS_MIN_RATIO:g})",
        fontsize=10,
    )
    fig.colorbar(shown, ax=ax[1], fraction=0.03)
    _save(fig, out / "stability_ds.png")
    masked = 100.0 * (ok & ~mask).sum() / max(ok.sum(), 1)
    rows = [
        [
            "validity limit acos(-w2)",
            f"{math.degrees(limit):.2f} deg",
            f"{ds_radial_resolution(model, limit):.0f}",
        ],
        [
            f"mask: radial >= {DS_MIN_RATIO:g} x centre",
            f"{math.degrees(stable):.2f} deg",
            f"{DS_MIN_RATIO * radial[0]:.0f}",
        ],
        *[
            [f"image {k}", f"{v:.2f} deg", f"{ds_radial_resolution(model, math.radians(v)):.0f}"]
            for k, v in edge_deg.items()
        ],
        ["image pixels masked", f"{masked:.3f} %", ""],
    ]
    return _table(["DS lens", "angle off axis", "radial px/rad"], rows)


# -- 2. Disparity -> depth ----------------------------------------------------------------


def disparity_chart(out: Path) -> str:
    rig = read_rig(REFERENCE_RIG)
    B, H = rig.baseline_m(), 2048
    theta = np.radians(np.linspace(0.25, 179.75, 720))[:, None]
    r = np.geomspace(0.3, 100.0, 500)[None, :]
    err = disparity_range_error(theta, r, B, H, DISP_ERROR_PX)
    limit = GtParams().stability_max_rel_error
    fig, ax = plt.subplots(1, 2, figsize=(15, 5.2), constrained_layout=True)
    log = np.log10(np.clip(np.where(np.isfinite(err), err, 1e3), 1e-3, 1e3))
    extent = (math.log10(0.3), math.log10(100.0), 180.0, 0.0)
    shown = ax[0].imshow(log, aspect="auto", extent=extent, vmin=-3, vmax=1, cmap="magma_r")
    levels = [0.01, 0.05, 0.1, limit]
    cs = ax[0].contour(
        np.log10(r[0]),
        np.degrees(theta[:, 0]),
        log,
        np.log10(levels),
        colors="cyan",
        linewidths=[0.8, 0.8, 0.8, 2.0],
    )
    ax[0].clabel(cs, fmt={np.log10(v): f"{100 * v:g} %" for v in levels}, fontsize=8)
    ax[0].set_xticks(np.log10([0.3, 1, 3, 10, 30, 100]), ["0.3", "1", "3", "10", "30", "100"])
    ax[0].set_xlabel("range [m]")
    ax[0].set_ylabel("latitude theta from 'up' (-y_rect) [deg]")
    ax[0].set_title(
        f"relative range error from +-{DISP_ERROR_PX} px disparity (B {B * 1e3:.0f} mm, H_full {H});"
        f" thick: the pipeline's mask ({100 * limit:g} %)",
        fontsize=9,
    )
    fig.colorbar(shown, ax=ax[0], label="log10 relative error")
    rows = []
    for level in (0.05, 0.1, limit):
        ok = err <= level
        far = np.where(ok.any(axis=1), np.where(ok, r, 0.0).max(axis=1), np.nan)
        ax[1].semilogy(np.degrees(theta[:, 0]), far, label=f"error <= {100 * level:g} %")
        cells = [f"{np.interp(t, np.degrees(theta[:, 0]), np.nan_to_num(far)):.1f}" for t in (5, 15, 45, 90)]
        rows.append([f"{100 * level:g} %", *cells])
    ax[1].set_xlabel("latitude theta [deg]")
    ax[1].set_ylabel("farthest stable range [m]")
    ax[1].set_title("how far disparity still gives depth (0 near the poles)")
    ax[1].grid(alpha=0.3, which="both")
    ax[1].legend()
    _save(fig, out / "stability_disparity.png")
    return _table(["rel. error limit", "theta 5 deg", "15 deg", "45 deg", "90 deg (farthest range, m)"], rows)


# -- 3. Cubemap seams ---------------------------------------------------------------------


def cubemap_chart(out: Path, bag: Path, dataset: Path) -> str:
    import cv2
    import yaml

    truth = Truth.load(bag)
    sid = sorted(p.stem for p in (dataset / "meta").glob("*.json"))[0]
    stamp = read_meta(dataset, sid).stamp_ns
    upper = cv2.imread(str(dataset / "left_fisheye" / f"{sid}.png"))
    lower = cv2.imread(str(dataset / "right_fisheye" / f"{sid}.png"))
    assert upper is not None and lower is not None
    height = int(yaml.safe_load((dataset / "dataset.yaml").read_text())["height_full"])
    results = compare_projections(upper, lower, truth.rig, height, lambda r: truth.range_along(r, stamp))
    reach = num_disparities_for(height / math.pi, truth.rig.baseline_m())
    fig, ax = plt.subplots(1, 3, figsize=(17, 4.8), constrained_layout=True, width_ratios=[1, 1, 1.3])
    rows = []
    for res in results[1:]:
        gt, disp, stable = res.maps["gt"], res.maps["disp"], res.maps["stable"]
        F = gt.shape[0]
        faces = [k for k in range(6) if np.isfinite(gt[:, k * F : (k + 1) * F]).any()]
        g, d, s = (np.stack([a[:, k * F : (k + 1) * F] for k in faces]) for a in (gt, disp, stable))
        ok, matched = np.isfinite(g), np.isfinite(d)
        with np.errstate(invalid="ignore"):
            bad = np.abs(d - g) > 1.0
        for axes_sum, a in (((0, 2), ax[0]), ((0, 1), ax[1])):  # per row (from the top), per column
            n = ok.sum(axis=axes_sum)
            m = (ok & matched).sum(axis=axes_sum)
            b = (ok & matched & bad).sum(axis=axes_sum)
            lw = 2.5 if res.name == "cubemap" else 1.0
            with np.errstate(invalid="ignore", divide="ignore"):
                a.plot(np.arange(F), 100 * m / n, lw=lw, label=f"{res.name}: matched")
                a.plot(
                    np.arange(F),
                    100 * b / np.maximum(m, 1),
                    lw=lw,
                    ls="--",
                    label=f"{res.name}: bad-1 of matched",
                )
        good = ok & matched & ~bad
        inside, outside = (100 * (good & sel).sum() / max((ok & sel).sum(), 1) for sel in (s, ~s))
        rows.append([res.name, f"{100 * (ok & s).sum() / ok.sum():.1f}", f"{inside:.1f}", f"{outside:.1f}"])
    eq = results[0]
    rows.insert(0, [eq.name, f"{100 * eq.stereo_stable.n_gt / eq.stereo.n_gt:.1f}", "", ""])
    F = results[1].maps["gt"].shape[0]
    ax[0].axvline(reach + 2, color="k", lw=1, label=f"mask edge: search range {reach} px + block radius")
    ax[0].set_xlabel("face row v (0 = the top edge, towards the up face)")
    ax[1].set_xlabel("face column u (left and right seams)")
    for a in ax[:2]:
        a.set_ylabel("% of GT pixels")
        a.grid(alpha=0.3)
        a.set_ylim(0, 102)
    ax[0].legend(fontsize=7, loc="center right")
    ax[0].set_title(f"SGBM on the side faces ({F} px, matched pitch)", fontsize=10)
    ax[1].set_title("the same per column: block margins at the side seams", fontsize=10)
    cube = results[1]
    err = np.abs(cube.maps["disp"] - cube.maps["gt"])[:, : 2 * F]
    cmap = plt.get_cmap("magma").with_extremes(bad="0.8")
    shown = ax[2].imshow(err, vmin=0, vmax=3, cmap=cmap)
    ax[2].contour(cube.maps["stable"][:, : 2 * F].astype(float), [0.5], colors="cyan", linewidths=1)
    ax[2].set_title("front | right face: |SGBM - exact| [px]; grey: no match; cyan: seam mask", fontsize=10)
    ax[2].set_xticks([])
    ax[2].set_yticks([])
    fig.colorbar(shown, ax=ax[2], fraction=0.03)
    _save(fig, out / "stability_cubemap.png")
    return _table(
        ["projection", "GT pixels in the mask %", "within 1 px inside %", "within 1 px outside %"], rows
    )


# -- 4./5. Time offsets and extrinsic errors ---------------------------------------------


@dataclass
class _Tally:
    """Pixel counts and errors of one case, pooled over samples."""

    n: int = 0
    bad: int = 0
    kept: int = 0
    kept_bad: int = 0
    errors: list[np.ndarray[Any, Any]] = field(default_factory=list)
    kept_errors: list[np.ndarray[Any, Any]] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        e, ek = np.concatenate(self.errors), np.concatenate(self.kept_errors)
        return {
            "outliers_pct": 100 * self.bad / max(self.n, 1),
            "kept_outliers_pct": 100 * self.kept_bad / max(self.kept, 1),
            "median_mm": 1e3 * float(np.median(e)),
            "kept_median_mm": 1e3 * float(np.median(ek)) if len(ek) else math.nan,
            "kept_pct": 100 * self.kept / max(self.n, 1),
            "pixels": float(self.n),
        }


MaskFn = Callable[[np.ndarray[Any, Any], SampleMeta], np.ndarray[Any, Any]]


def _score_offsets(dataset: Path, truth: Truth, cases: list[tuple[float, MaskFn]]) -> list[dict[str, float]]:
    """Errors of the written depth GT vs the truth at (stamp - dt ms) for every (dt, mask) case."""
    model = truth.rig.upper.model
    tallies = [_Tally() for _ in cases]
    for meta_path in sorted((dataset / "meta").glob("*.json")):
        sid = meta_path.stem
        meta = read_meta(dataset, sid)
        depth = read_png_u16(dataset / "depth_fisheye" / f"{sid}.png", DEPTH_SCALE)
        rows, cols = np.nonzero(depth)
        pixels = np.stack([cols, rows], 1).astype(np.float64)
        for (dt, make_mask), t in zip(cases, tallies, strict=True):
            exact = truth.range_at(model, pixels, meta.stamp_ns - round(dt * 1e6))
            e = depth[rows, cols] - exact
            ok = np.isfinite(e)
            bad = ok & (np.abs(e) > np.maximum(0.05, 0.03 * np.nan_to_num(exact)))
            keep = make_mask(depth, meta)[rows, cols] & ok
            t.n += int(ok.sum())
            t.bad += int(bad.sum())
            t.kept += int(keep.sum())
            t.kept_bad += int((bad & keep).sum())
            t.errors.append(np.abs(e[ok]))
            t.kept_errors.append(np.abs(e[keep]))
    return [t.summary() for t in tallies]


def _offset_chart(
    xs: list[float], stats: list[dict[str, float]], xlabel: str, title: str, path: Path
) -> None:
    fig, ax = plt.subplots(1, 2, figsize=(14, 4.8), constrained_layout=True)
    ax[0].plot(xs, [s["outliers_pct"] for s in stats], "o-", label="all GT")
    ax[0].plot(xs, [s["kept_outliers_pct"] for s in stats], "o-", label="GT kept by the displacement mask")
    ax[0].axhline(0.5, color="k", ls=":", lw=1, label="target 0.5 %")
    ax[0].set_ylabel("outliers, |e| > max(5 cm, 3 %) [%]")
    ax[1].plot(xs, [s["median_mm"] for s in stats], "o-", label="median |e|, all GT")
    ax[1].plot(xs, [s["kept_median_mm"] for s in stats], "o-", label="median |e|, kept GT")
    ax[1].set_ylabel("median |depth error| [mm]")
    twin = ax[1].twinx()
    twin.plot(xs, [s["kept_pct"] for s in stats], "s--", color="tab:green", label="GT kept [%]")
    twin.set_ylabel("share of GT the mask keeps [%]", color="tab:green")
    twin.set_ylim(0, 105)
    for a in ax:
        a.set_xlabel(xlabel)
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    lines = ax[1].get_legend_handles_labels()[0] + twin.get_legend_handles_labels()[0]
    ax[1].legend(lines, [h.get_label() for h in lines], fontsize=8, loc="upper left")
    fig.suptitle(title, fontsize=11)
    _save(fig, path)


def _offset_table(label: str, xs: list[float], stats: list[dict[str, float]]) -> str:
    keys = ("outliers_pct", "kept_outliers_pct", "median_mm", "kept_median_mm", "kept_pct")
    rows = [
        [f"{x:g}", *(f"{s[k]:.3f}" if "outliers" in k else f"{s[k]:.2f}" for k in keys)]
        for x, s in zip(xs, stats, strict=True)
    ]
    head = [label, "outliers % (all)", "outliers % (kept)", "median mm (all)", "median mm (kept)", "kept %"]
    return _table(head, rows)


def time_offset_chart(out: Path, bag: Path, dataset: Path) -> str:
    truth = Truth.load(bag)
    ppr = px_per_rad(truth.rig.upper.model)

    def mask_for(dt_s: float) -> MaskFn:
        def make(depth: np.ndarray[Any, Any], meta: SampleMeta) -> np.ndarray[Any, Any]:
            motion = meta.motion
            span_s = max(meta.lidar_skew_ms.values()) / 1e3
            omega = math.radians(motion.max_rotation_deg) / max(span_s, 1e-3)
            speed = motion.speed_mps
            disp = time_offset_displacement_px(dt_s, omega, speed, np.where(depth > 0, depth, 1.0), ppr)
            return displacement_mask(depth, disp, time_offset_range_error_m(dt_s, speed))

        return make

    cases = [(dt, mask_for(dt / 1e3)) for dt in OFFSETS_MS]
    stats = _score_offsets(dataset, truth, cases)
    _offset_chart(
        list(OFFSETS_MS),
        stats,
        "camera stamp late by [ms] (LiDAR-camera time offset)",
        "Time offset on a simulated walk (1.2 m/s, up to 60 deg/s): GT scored against the truth "
        "at the image's real time",
        out / "stability_time_offset.png",
    )
    return _offset_table("offset ms", list(OFFSETS_MS), stats)


def _rotated_rig(rig_path: Path, angle_deg: float, folder: Path) -> Path:
    rig = read_rig(rig_path)
    R4 = np.eye(4)
    R4[:3, :3] = rotvec_to_matrix((EXTRINSIC_AXIS * math.radians(angle_deg))[None])[0]
    lidars = tuple(replace(li, T_cam0_lidar=li.T_cam0_lidar @ R4) for li in rig.lidars)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "rig.yaml"
    write_rig(replace(rig, lidars=lidars), path, camchain_name="camchain.yaml")
    return path


def extrinsic_chart(out: Path, bag: Path, work: Path) -> str:
    truth = Truth.load(bag)
    ppr = px_per_rad(truth.rig.upper.model)
    lever = max(float(np.linalg.norm(li.T_cam0_lidar[:3, 3])) for li in truth.rig.lidars)
    stats = []
    for angle in ANGLES_DEG:
        folder = work / f"extrinsic_{angle:g}"
        rig = _rotated_rig(truth.path / "rig.yaml", angle, folder)
        ingest([bag], IngestConfig(rig=rig, out=folder / "ds", workers=2, every=2))
        a = math.radians(angle)

        def make(depth: np.ndarray[Any, Any], meta: SampleMeta, a: float = a) -> np.ndarray[Any, Any]:
            disp = extrinsic_displacement_px(a, np.where(depth > 0, depth, 1.0), lever, ppr)
            return displacement_mask(depth, disp, extrinsic_range_error_m(a, lever))

        stats += _score_offsets(folder / "ds", truth, [(0.0, make)])
    _offset_chart(
        list(ANGLES_DEG),
        stats,
        "rotation error of T_cam0_lidar (both LiDARs) [deg]",
        "Extrinsic error on a simulated static room: GT scored against the truth",
        out / "stability_extrinsic.png",
    )
    return _offset_table("error deg", list(ANGLES_DEG), stats)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=DOCS, help="folder for the charts")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale of the simulated rig")
    args = parser.parse_args()
    t0 = time.perf_counter()
    print("# 1. Double Sphere near its validity limit\n")
    print(ds_chart(args.out))
    print("\n# 2. Disparity -> depth: farthest range within the error (0.5 px, reference rig, H_full 2048)\n")
    print(disparity_chart(args.out))
    common: dict[str, Any] = {"scale": args.scale, "image": "jpeg", "range_noise_m": 0.0}
    with tempfile.TemporaryDirectory(prefix="bench-stability-") as tmp:
        work = Path(tmp)
        room = simulate(SimConfig(scene="indoor", duration_s=0.3, seed=1, **common), work / "room").bag
        walk = simulate(
            SimConfig(scene="outdoor", trajectory="walk", duration_s=0.5, seed=2, **common), work / "walk"
        ).bag
        room_ds = work / "room_ds"
        ingest([room], IngestConfig(rig=Truth.load(room).path / "rig.yaml", out=room_ds, workers=2, every=4))
        print("\n# 3. Cubemap seams (SGBM, simulated room)\n")
        print(cubemap_chart(args.out, room, room_ds))
        walk_ds = work / "walk_ds"
        ingest([walk], IngestConfig(rig=Truth.load(walk).path / "rig.yaml", out=walk_ds, workers=2))
        print("\n# 4. LiDAR-camera time offset (simulated walk)\n")
        print(time_offset_chart(args.out, walk, walk_ds))
        print("\n# 5. Extrinsic rotation error (simulated room)\n")
        print(extrinsic_chart(args.out, room, work))
    print(f"\ncharts in {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
