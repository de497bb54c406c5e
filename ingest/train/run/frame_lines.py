"""The warning lines of `ingest.train.run.frame_check`'s findings: what each names, what it means and
what to do, one line per finding."""

from __future__ import annotations

from ingest.train.run.frame_check import (
    FIT_MATCH,
    FLAT_MORE,
    MIN_SAMPLES,
    OFF_IMAGE_DEG,
    PAIR_OFF_PX,
    PAIR_QUADRANT_PX,
    PAIR_SHIFT_PX,
    PART_MATCH,
    POOR_MATCH,
    SCATTER_MIN,
    SCATTER_OUT,
    SWAP_MIN,
    FrameFlags,
    kind,
)


def lower_off_line(ids: list[str], samples: int) -> str:
    """One line for lower images off their points in most samples (`FrameFlags.lower_off_most`) that the
    stereo pose's check does not explain: each sample's lower image lies off in its own way, so it is no
    fixed pose error but frames out of place (reordered, or a lower camera whose stamps are not its own)."""
    shown = ", ".join(ids[:5]) + (", ..." if len(ids) > 5 else "")
    return (
        f"{len(ids)} of {samples} samples have a lower image that lies off every LiDAR's points by over "
        f"{OFF_IMAGE_DEG:g} deg ({shown}), each its own way (no stereo pose explains them): the lower "
        "camera's frames are not the ones taken at their stamps (reordered, or stamped by another clock); "
        "the samples are written and flagged in the summary: leave them out of training, and check cam1's "
        "stamps"
    )


def pair_off_line(flags: FrameFlags) -> str:
    """One line when the run's median pair shift passes `PAIR_OFF_PX` ('' otherwise): every pair sits off
    where its disparity GT lays the lower image onto the upper, which no frame fault does to most samples
    alike: the camchain's stereo pose (baseline length or rotation) is not the cameras', or the GT's points
    are not where the images saw them (a clock offset, range noise), which the run's other lines name."""
    dx, dy = flags.pair_shift_median
    if flags.pair_shift_samples < MIN_SAMPLES or max(abs(dx), abs(dy)) <= PAIR_OFF_PX:
        return ""
    return (
        f"the lower images sit {dx:+.2f} px across and {dy:+.2f} px along the epipolar lines from where the "
        f"disparity GT lays them onto the upper images (median over {flags.pair_shift_samples} samples; a "
        f"right camchain gives under {PAIR_OFF_PX:g} px), so the disparity GT does not hold for the pairs: "
        "the camchain's stereo pose (its baseline length or rotation, T_cn_cnm1) is not the cameras', or the "
        "GT's points are not where the images saw them (a clock offset or range noise, which the other "
        "warnings then name); with none, calibrate the pair again or correct the camchain"
    )


def flag_lines(flags: FrameFlags) -> list[str]:
    """One warning line per finding, naming its samples (the first five), out of the samples judged, and
    `pair_off_line` when it has one."""
    judged = flags.samples
    lines = [line] if (line := pair_off_line(flags)) else []
    for what, ids in flags.found.items():
        shown = ", ".join(ids[:5]) + (", ..." if len(ids) > 5 else "")
        lines.append(f"{len(ids)} of {judged} samples have {_phrase(what, flags)} ({shown}): {_cause(what)}")
    return lines


def _phrase(what: str, flags: FrameFlags) -> str:
    """The finding `what` (a `kind`) as the warning line says it."""
    if what.endswith("out of place against the rest"):
        lidar = what.split("'s points")[0]
        return (
            f"a stretch of {lidar}'s window whose points match the upper image below {PART_MATCH:g} of "
            f"what its other stretches do, or lie near their points below {FIT_MATCH:g} as often"
        )
    if what.endswith("far more than in the run's other samples"):
        lidar = what.split("'s ranges")[0]
        return (
            f"{lidar}'s ranges scattering against the first LiDAR's where cam0 sees both in a pixel by over "
            f"{SCATTER_OUT:g} times the run's median and {SCATTER_MIN:.0%}"
        )
    if what.endswith("'s points matching the upper image far worse than the run's"):
        lidar = what.split("'s points")[0]
        return (
            f"{lidar}'s points matching the upper image far worse than in the run's other samples (below "
            f"{POOR_MATCH:g} of its median correlation, {flags.correlation_median['upper'][lidar]:.2f}), "
            "while the other LiDARs' match"
        )
    camera = "upper" if what.startswith("upper image") else "lower"
    article = "an" if camera == "upper" else "a"
    if what == kind("", "identical"):
        return "identical upper and lower images"
    if what == kind("", "shifted"):
        dx, dy = flags.pair_shift_median
        return (
            f"a lower image shifted against its upper image by over {PAIR_SHIFT_PX:g} px (or a quadrant of "
            f"it by over {PAIR_QUADRANT_PX:g} px) more than the run's other pairs, across or along the "
            "epipolar lines, where the disparity GT lays one onto the other (the run's median shift "
            f"{dx:+.2f} px across, {dy:+.2f} px along)"
        )
    if what == kind("", "swapped"):
        return (
            f"upper and lower images whose colour balances (log red/blue) differ by over {SWAP_MIN:g} and "
            "are each other's negative"
        )
    if what == kind(camera, "off"):
        return f"{article} {camera} image that lies off every LiDAR's points by over {OFF_IMAGE_DEG:g} deg"
    if what == kind(camera, "repeat"):
        return f"{article} {camera} image that repeats its camera's frame before it to the byte"
    if what == kind(camera, "poor"):
        medians = ", ".join(f"{k} {v:.2f}" for k, v in sorted(flags.correlation_median[camera].items()))
        return (
            f"{article} {camera} image the LiDAR points match far worse than the run's others "
            f"(below {POOR_MATCH:g} of the median correlation: {medians})"
        )
    return (
        f"{article} {camera} image that is one flat grey level over {FLAT_MORE:.0%} more of it than the "
        f"run's others (median {flags.flat_median[camera]:.0%}) or over all of it"
    )


def _cause(what: str) -> str:
    """What the finding `what` means and what to do."""
    tail = "the samples are written and flagged in the summary: leave them out of training"
    if what == kind("", "identical"):
        return f"one camera's frame was published on both cameras' topics; {tail}"
    if what == kind("", "shifted"):
        return (
            "one camera's frame is moved against the other's and against the GT (a readout glitch, a frame "
            f"of another moment, a camera knocked), so the disparity GT does not hold for the pair; {tail}"
        )
    if what == kind("", "swapped"):
        return (
            "one camera's images carry red and blue in the other order (a driver publishing rgb8 bytes as "
            f"bgr8 or the reverse, or a frame labelled with another encoding than its camera's); {tail}"
        )
    if what.endswith("over much of it"):
        return f"a black, saturated or torn frame; {tail}"
    if what.endswith("the frame before it"):
        return f"a camera or driver that sent its last frame again under a new stamp; {tail}"
    if what.endswith("out of place against the rest"):
        return (
            "the LiDAR's sweep there is not where its pose and its own other points put it (a glitched "
            f"sweep: points turned, moved or mirrored, or another moment's); {tail}"
        )
    if what.endswith("far more than in the run's other samples"):
        return (
            "in those windows one of the two LiDARs' points land apart from where the other's put the "
            f"surfaces (a sweep turned, moved or of another moment); {tail}"
        )
    if what.endswith("'s points matching the upper image far worse than the run's"):
        return (
            "the LiDAR's points in those windows are not where its pose puts them (a sweep with another "
            f"unit's points, an axis flipped, or a sweep whose time is wrong); {tail}"
        )
    if "far worse" in what:
        return f"each image is not this camera's frame of its stamp (another frame, turned or torn); {tail}"
    return (
        "each image is not the one taken at its stamp (a frame published under another's stamp, or a camera "
        f"clock that jumped); {tail}"
    )
