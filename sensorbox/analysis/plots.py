"""Matplotlib figures for people to look at (rig layout, samples, clock offsets, statistics)."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from calibration.report import RigReport
from calibration.rig import Rig
from calibration.types import F64
from ingest.dataset.layout import write_atomic, write_atomic_set
from ingest.errors import DatasetError

# Plot frame: cam0 rotated so that x = forward, y = left, z = up (a familiar robot view).
_R_VIEW_CAM0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
_COLORS = {"camera": "tab:blue", "lidar": "tab:red", "imu": "tab:green"}
LIDAR_VFOV_DEG = (-7.0, 52.0)


def figure_bytes(fig: Figure, path: str | Path, dpi: int) -> bytes:
    """A figure rendered in memory in the format of `path`'s suffix (PNG when it has none); closes it.

    Rendering before anything is written lets a caller write a chart and its
    data as one set (`ingest.dataset.layout.write_atomic_set`).
    """
    out = Path(path)
    try:
        fmt = out.suffix.lstrip(".").lower() or "png"
        if fmt not in fig.canvas.get_supported_filetypes():
            known = ", ".join(sorted(fig.canvas.get_supported_filetypes()))
            raise DatasetError(f"{out}: cannot draw a .{fmt} file; give a name ending in one of {known}")
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, dpi=dpi)
    finally:
        plt.close(fig)
    return buf.getvalue()


def _save(fig: Figure, path: str | Path, dpi: int) -> Path:
    """Write a figure (creating its folder), close it, return the path.

    The format is the file's suffix (PNG when it has none, never a suffix
    added behind the user's back); the figure is rendered in memory and
    written atomically, so a full disk, a read-only folder or a folder given
    as `path` is one `OutputError` naming `path` and leaves no partial file.
    """
    out = Path(path)
    data = figure_bytes(fig, out, dpi)
    out.parent.mkdir(parents=True, exist_ok=True)  # an OSError here names the folder (CLI: exit 3)
    write_atomic(out, data)
    return out


def _fov_rays_camera(rig: Rig, name: str, n: int = 181) -> tuple[F64, F64]:
    """Border rays of a camera's central row and column, in cam0 (unit)."""
    cam = rig.camera(name)
    m = cam.model
    cx = float(getattr(m, "cx", (m.width - 1) / 2))
    cy = float(getattr(m, "cy", (m.height - 1) / 2))
    row = np.stack([np.linspace(-0.5, m.width - 0.5, n), np.full(n, cy)], axis=-1)
    col = np.stack([np.full(n, cx), np.linspace(-0.5, m.height - 0.5, n)], axis=-1)
    R = cam.T_cam0_cam[:3, :3]
    out = []
    for uv in (row, col):
        rays, valid = m.unproject(uv)
        out.append(rays[valid] @ R.T)
    return out[0], out[1]


def plot_rig(rig: Rig, report: RigReport, path: str | Path, cone_m: float = 0.15) -> Path:
    """Draw the rig from the top and the side: frames with axes, camera and LiDAR FOV cones."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.5))
    views = [("Top view (x forward, y left)", 0, 1), ("Side view (x forward, z up)", 0, 2)]
    for ax, (title, i, j) in zip(axes, views, strict=True):
        for fr in report.frames:
            p = _R_VIEW_CAM0 @ fr.position_m
            R = _R_VIEW_CAM0 @ fr.T_cam0_sensor[:3, :3]
            color = _COLORS.get(fr.kind, "k")
            ax.plot(p[i], p[j], "o", color=color, ms=6)
            for axis, c in zip(range(3), ("r", "g", "b"), strict=True):
                a = R[:, axis] * 0.04
                ax.annotate(
                    "",
                    (p[i] + a[i], p[j] + a[j]),
                    (p[i], p[j]),
                    arrowprops={"arrowstyle": "->", "color": c, "lw": 1.2},
                )
            ax.annotate(
                fr.name,
                (p[i], p[j]),
                textcoords="offset points",
                xytext=(6, -12),
                fontsize=8,
                color=color,
            )
            if fr.kind == "camera":
                h_rays, v_rays = _fov_rays_camera(rig, fr.name)
                rays = h_rays if j == 1 else v_rays
                pts = (_R_VIEW_CAM0 @ rays.T).T * cone_m + p
                ax.fill(
                    np.r_[p[i], pts[:, i], p[i]],
                    np.r_[p[j], pts[:, j], p[j]],
                    color=color,
                    alpha=0.12,
                )
            if fr.kind == "lidar" and j == 2:
                for el in LIDAR_VFOV_DEG:
                    for az in (0.0, np.pi):
                        e = np.radians(el)
                        d_l = np.array([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)])
                        d = R @ d_l * cone_m * 1.5
                        ax.plot([p[i], p[i] + d[i]], [p[j], p[j] + d[j]], color=color, lw=0.8, alpha=0.6)
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_xlabel("forward [m]")
        ax.set_ylabel("left [m]" if j == 1 else "up [m]")
    base = f", baseline {report.baseline_m * 1000:.1f} mm" if report.baseline_m else ""
    fig.suptitle(f"Rig '{report.name}'{base}  (axes: x red, y green, z blue; cones = FOV)")
    fig.tight_layout()
    return _save(fig, path, dpi=110)


PREVIEW_WIDTH_PX = 960  # each panel is drawn from an image this wide at most (the figure shows less)


def _shrunk(image: np.ndarray, gt: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The panel's image (area-averaged) and GT (the largest value of each block, so a lone point
    stays visible) at most `PREVIEW_WIDTH_PX` wide."""
    import cv2

    h, w = image.shape[:2]
    step = max(1, int(np.ceil(w / PREVIEW_WIDTH_PX)))
    if step == 1:
        return image, gt
    hs, ws = h // step, w // step
    small = cv2.resize(image[: hs * step, : ws * step], (ws, hs), interpolation=cv2.INTER_AREA)
    if gt is None:
        return small, None
    blocks = gt[: hs * step, : ws * step].reshape(hs, step, ws, step)
    return small, blocks.max(axis=(1, 3))  # the largest value of each block: a lone point stays


def plot_sample(dataset_dir: Path, sid: str, out: Path) -> Path:
    """Preview of one written sample: fisheye with its range GT, the rectified pair with disparity GT.

    GT is painted into the image (a colour per valid pixel) rather than
    scattered as markers: dense GT has a million valid pixels, which
    matplotlib's scatter took seconds to draw.
    """
    import cv2

    from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE, read_png_u16

    def rgb(folder: str) -> np.ndarray:
        img = cv2.imread(str(dataset_dir / folder / f"{sid}.png"))
        return np.asarray(img)[..., ::-1]

    depth = read_png_u16(dataset_dir / "depth_fisheye" / f"{sid}.png", DEPTH_SCALE)
    disp = read_png_u16(dataset_dir / "disp_equirect" / f"{sid}.png", DISP_SCALE)
    fig, axes = plt.subplots(2, 2, figsize=(14, 9), constrained_layout=True)
    panels = [
        (axes[0, 0], rgb("left_fisheye"), depth, "left_fisheye + depth_fisheye (range, m)"),
        (axes[0, 1], rgb("right_fisheye"), None, "right_fisheye"),
        (axes[1, 0], rgb("equirect_up"), disp, "equirect_up + disp_equirect (px)"),
        (axes[1, 1], rgb("equirect_down_virt"), None, "equirect_down_virt"),
    ]
    cmap = matplotlib.colormaps["turbo"]
    for ax, full, full_gt, title in panels:
        image, gt = _shrunk(full, full_gt)
        if gt is not None:
            valid = gt > 0
            values = full_gt[full_gt > 0] if full_gt is not None else gt[valid]
            lo, hi = (float(values.min()), float(values.max())) if values.size else (0.0, 1.0)
            norm = matplotlib.colors.Normalize(lo, hi)
            image = image.copy()
            image[valid] = (cmap(norm(gt[valid]))[:, :3] * 255).astype(np.uint8)
            fig.colorbar(matplotlib.cm.ScalarMappable(norm, cmap), ax=ax, shrink=0.7)
        ax.imshow(image, interpolation="nearest")
        ax.set_title(f"{title} [{sid}]")
        ax.set_axis_off()
    return _save(fig, out, dpi=90)


# ---- evaluation and dataset statistics (sensorbox eval / stats) ----------------------------

import typing  # noqa: E402  (this section is appended; its types are only for the checker)

if typing.TYPE_CHECKING:
    from ingest.train.run.refine import Refinement


def draw_heatmap(hm: Heatmap, path: str | Path, title: str) -> bytes:
    """A metric over FOV (rows) x baseline (columns), each cell annotated with its value, as the bytes
    of the image file `path` (its suffix picks the format)."""
    from ingest.eval.report import format_metric

    fig, ax = plt.subplots(figsize=(1.6 * len(hm.baselines_mm) + 3.0, 1.0 * len(hm.fovs_deg) + 2.2))
    percent = hm.metric in ("bad1", "bad2", "bad3", "delta1", "delta2", "delta3", "coverage")
    shown = hm.values * (100.0 if percent else 1.0)
    im = ax.imshow(np.ma.masked_invalid(shown), cmap="viridis", aspect="auto")
    finite = shown[np.isfinite(shown)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
    for i in range(len(hm.fovs_deg)):
        for j in range(len(hm.baselines_mm)):
            text = format_metric(hm.metric, float(hm.values[i, j]))
            light = bool(shown[i, j] > lo + 0.6 * (hi - lo))  # viridis is light at the top: dark text
            ax.text(j, i, text, ha="center", va="center", color="k" if light else "w", fontsize=10)
    ax.set_xticks(range(len(hm.baselines_mm)), [f"{b:g} mm" for b in hm.baselines_mm])
    ax.set_yticks(range(len(hm.fovs_deg)), [f"{f:g}°" for f in hm.fovs_deg])
    ax.set_xlabel("baseline")
    ax.set_ylabel("FOV")
    fig.colorbar(im, ax=ax, label=f"{hm.metric}{' [%]' if percent else ''}")
    ax.set_title(title)
    fig.tight_layout()
    return figure_bytes(fig, path, dpi=110)


def draw_stats(stats: DatasetStats, path: str | Path) -> bytes:
    """Histograms of a dataset, as file bytes: depth distribution (pixels), GT density and mean local
    entropy (samples)."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    shares = [0.0 if not np.isfinite(s) else 100.0 * s for s in stats.depth_shares]
    axes[0].bar(stats.bins, shares, color="tab:blue")
    axes[0].set_ylabel("valid GT pixels [%]")
    axes[0].set_title("depth distribution")
    density = [100.0 * s.density for s in stats.samples]
    axes[1].hist(density, bins=min(30, max(5, len(density))), color="tab:green")
    axes[1].set_xlabel("GT density [% of pixels]")
    axes[1].set_ylabel("samples")
    axes[1].set_title(f"GT density (mean {100.0 * stats.density_mean:.2f} %)")
    entropy = [s.entropy_bits for s in stats.samples if np.isfinite(s.entropy_bits)]
    axes[2].hist(entropy, bins=min(30, max(5, len(entropy))), color="tab:orange")
    axes[2].set_xlabel("mean local entropy, 11x11 [bits]")
    axes[2].set_ylabel("samples")
    axes[2].set_title(f"texture (mean {stats.entropy_mean_bits:.3f} bits)")
    fig.suptitle(f"{stats.dataset} ({stats.layout} layout, {len(stats.samples)} samples)")
    fig.tight_layout()
    return figure_bytes(fig, path, dpi=100)


def write_stats(stats: DatasetStats, folder: Path) -> tuple[Path, Path]:
    """`sensorbox stats`' output set, FOLDER/stats.json and FOLDER/stats.png: both written, or neither.

    The chart is drawn in memory first, then both files are written with
    `write_atomic_set`, so a full disk leaves no stats.json without its chart
    (nor an old pair half replaced).
    """
    import json

    doc = (json.dumps(stats.to_json(), indent=1) + "\n").encode()
    json_path, png_path = folder / "stats.json", folder / "stats.png"
    write_atomic_set([(json_path, doc), (png_path, draw_stats(stats, png_path))])
    return json_path, png_path


if typing.TYPE_CHECKING:
    from ingest.eval.report import Heatmap
    from ingest.eval.stats import DatasetStats


def plot_timeshift(refinement: Refinement, path: str | Path) -> Path:
    """Per camera: the rotation residual (RMS, deg) against the clock offset tried, the rig's value and
    the estimate marked, so a person sees how sharp (observable) the minimum is."""
    cams = refinement.cameras
    fig, axes = plt.subplots(1, len(cams), figsize=(5 * len(cams), 3.6), squeeze=False)
    for ax, cam in zip(axes[0], cams, strict=True):
        e = cam.estimate
        ax.plot(e.offsets_ms, np.sqrt(e.cost), color="tab:blue", lw=1.2, label="images vs gyro")
        ax.axvline(
            cam.rig_timeshift_ms, color="tab:gray", ls="--", lw=1, label=f"rig {cam.rig_timeshift_ms:+.2f} ms"
        )
        if e.observable:
            ax.axvline(
                e.timeshift_ms,
                color="tab:red",
                lw=1,
                label=f"estimate {e.timeshift_ms:+.2f} ± {e.sigma_ms:.2f} ms",
            )
        else:
            ax.set_title("not observable: the rig hardly turned", fontsize=9)
        ax.set_xlabel("timeshift_cam_imu [ms] (exposure = stamp + this)")
        ax.set_ylabel("rotation residual RMS [deg]")
        ax.set_title(
            f"{cam.camera}: {e.pairs} frame pairs, rate change {e.excitation_deg_s:.1f} deg/s", fontsize=9
        )
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path, 120)
