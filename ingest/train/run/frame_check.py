"""Frames that are not what their stamp and topic say: each sample's two images checked on their own and
against the LiDAR points, and the run's samples that stand out named once the run is over.

A single frame out of place writes a sample whose images do not belong to its ground truth while every
count looks right: a frame published under its neighbour's stamp, a frame from the other camera, a frame
that is blank or torn, a frame turned over. Each is found by what it does to a measurement the run makes
anyway, compared with the run's other samples, since the scene sets what "normal" is:

- the two images are the same pixels (one camera's frame published on both topics);
- the two images have red and blue swapped against each other (`SWAP_MIN`: a camera or a frame whose
  encoding says bgr8 for rgb8 bytes, or the reverse);
- an image is one flat grey level over much more of it than the run's others are (black, white, torn);
- a frame repeats its camera's frame before it to the byte (a camera or driver that sent its last frame
  again under a new stamp; a still rig's frames all repeat in a simulator that adds no noise, so the
  plan names them only when they are under half of the camera's frames);
- the LiDAR points' alignment with it moves them by over `OFF_IMAGE_DEG`;
- the points match it far worse than they match the run's other images of that camera (correlation of
  reflectivity and intensity below `POOR_MATCH` of the run's median);
- one stretch of a LiDAR's window matches the upper image far worse than the window's other stretches
  (below `PART_MATCH` of their median), or its points lie far from theirs (`FIT_MATCH`): that LiDAR's
  sweep there is out of place (a glitched sweep turned, moved or mirrored). This one needs no run median,
  so it holds however few samples share the fault;
- one LiDAR's ranges scatter against the first LiDAR's, where cam0 sees both in a pixel, far more than
  in the run's other samples (`SCATTER_OUT`): in that window one of them lands its points apart from the
  other's (a sweep turned or moved by a little);
- (of a sample none of these names) the lower rectified image sits shifted against the upper one at the
  disparity GT's pixels by over `PAIR_SHIFT_PX` more than the run's other pairs
  (`ingest.train.gt.stereo_offset`: one camera's frame moved by a readout glitch, a frame of another
  moment, a camera knocked).

A sample is named for the first of these that it shows, per camera. Most of a run's samples showing one
is not a frame out of place but a rig or camchain fault, which the calibration check names.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from ingest.dataset.meta import AlignmentMeta, FrameCheckMeta, SampleMeta

OFF_IMAGE_DEG = 1.0
OFF_IMAGE_PX = 2.0
"""A sample's image lies off its LiDAR points when every LiDAR's alignment moves them by more than this
(deg, and pixels of the camera): on the simulated walk the samples lie 0.06-0.44 deg off; a frame
published under its neighbour's stamp (33 ms away at 1.2 m/s), 1.9-2.0 deg."""
POOR_MATCH = 0.75
"""A sample's image matches the points far worse than the run's when every LiDAR's correlation is below
this fraction of its median over the run's samples (one LiDAR's alone: its points are out of place): on
the simulated fixtures a run's samples lie at 0.85-1.1 of its median (0.47-0.80 by scene); an image
turned over gives -0.35 to -0.05, half of it from the frame before 0.68, a sweep with its z flipped 0.29."""
FIT_MATCH = 0.6
MIN_FIT = 0.3
"""A stretch of a LiDAR's window is out of place too when the share of its points near the window's other
stretches' (`ingest.train.gt.window_fit.stretch_shares`) is below `FIT_MATCH` of the median stretch's,
where that median is above `MIN_FIT` (a sparse LiDAR's stretches barely meet: nothing to judge by). On
the simulated fixtures the stretches lie at 0.78 of the median and above; a sweep turned 5 deg about x
gives 0.40-0.45, the 90 deg turn 0.24-0.51."""
PART_MATCH = 0.5
MIN_PARTS = 4
"""A stretch of a LiDAR's window is out of place when its correlation with the upper image is below
`PART_MATCH` of the window's median stretch (`ingest.train.gt.align.part_correlations`, at least
`MIN_PARTS` of them measured): on the simulated fixtures every stretch lies at 0.55 of the median or above
(the emulated walk's scan pattern alternates 0.3 and 0.5); the stretches of a sweep turned 90 deg about
its axis give -0.07 to 0.22 against 0.49."""
SWAP_MIN = 0.2
SWAP_LEFT = 0.25
"""A sample's two images have red and blue swapped against each other when their colour balances
(`red_blue`, log red/blue) differ by over `SWAP_MIN` and swapping one would leave under `SWAP_LEFT` of
that difference: the simulated fixtures' two cameras agree within 0.01 (balances -0.16 to 0.07); the walk
with its lower camera's red and blue swapped differs by 0.26-0.32, with 0.01 left after a swap back. A
scene too grey to tell (a balance within 0.1 of zero) is not judged: a swap there hardly shows."""
FLAT_STEP_PX = 4
FLAT_BLOCK = 8
FLAT_LEVELS = 2
"""An image is flat where a block of `FLAT_BLOCK` x `FLAT_BLOCK` of its every `FLAT_STEP_PX`-th pixel
(32 x 32 pixels) spans at most `FLAT_LEVELS` grey levels: a black or saturated area, or the dark corners
of a fisheye."""
FLAT_MORE = 0.2
FLAT_ALL = 0.99
"""A sample's image is blank when it is flat over `FLAT_MORE` more of its area than the run's median
image of that camera (the corners a fisheye never lights are flat in every sample), or over `FLAT_ALL`."""
PAIR_SHIFT_PX = 0.5
"""A sample's pair is shifted when its lower image's shift against the upper (`SampleMeta.stereo_offset`)
differs from the run's median by over this, across or along the epipolar lines (px of the rectified
equirect): the simulated fixtures' pairs lie within 0.08 px of it, the walk with one lower frame moved 1 px
right (1.08 px of its 512-px equirect) 1.2 px off; a LiDAR's alignment onto a 480-px fisheye cannot tell
that frame from its others (0.98 against 0.57 px)."""
PAIR_QUADRANT_PX = 0.6
QUADRANTS = 4
"""... or one quadrant of its GT pixels' shift (`SampleMeta.stereo_offset_quadrants`) differs from the
run's median of that quadrant by over this: the fixtures' quadrants lie within 0.32 px of theirs (the dense
walk; sparse 0.2); an upper frame turned 1 deg about its centre (4 px at the edge of 480) 0.94 px, with its
whole shift 0.29."""
SCATTER_OUT = 3.0
SCATTER_MIN = 0.01
"""A sample's LiDARs disagree when one's ranges scatter against the first's (robust 1-sigma of their ratio
in the pixels cam0 sees both in, `ingest.train.gt.lidar_agreement.range_ratios`) by over this many times
the run's median and over this fraction: the fixtures' samples lie within 1.3 times their run's median
(0.12-0.89 % by scene); the room with one lidar_bottom sweep turned 2 deg about z 2.7 % against 0.16 %."""
PAIR_OFF_PX = 0.25
"""The run's pairs sit off their disparity GT when the median pair shift (`SampleMeta.stereo_offset`, over
at least `MIN_SAMPLES`) passes this across or along the epipolar lines (px of the rectified equirect): the
simulated fixtures' runs lie within 0.05 px; the room with the camchain's baseline 10 mm (8 %) short 0.47 px
along (its disparity GT 0.51 px off the truth), 2 mm short 0.1 px."""
MIN_MEDIAN = 0.2
"""Below this median correlation the points do not match the run's images well enough to measure by."""
MIN_SAMPLES = 3
"""The run's medians need this many samples; with fewer only the absolute tests apply."""


def flat_fraction(image: np.ndarray) -> float:
    """The fraction of `image` (BGR, BGRA or grey uint8/uint16) that is flat (`FLAT_LEVELS`)."""
    small = image[::FLAT_STEP_PX, ::FLAT_STEP_PX]
    if small.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if small.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        small = cv2.cvtColor(np.ascontiguousarray(small), code)
    if small.dtype != np.uint8:
        small = (small >> 8).astype(np.uint8)
    rows, cols = small.shape[0] // FLAT_BLOCK, small.shape[1] // FLAT_BLOCK
    if rows == 0 or cols == 0:
        return float(np.ptp(small) <= FLAT_LEVELS)
    blocks = small[: rows * FLAT_BLOCK, : cols * FLAT_BLOCK].reshape(rows, FLAT_BLOCK, cols, FLAT_BLOCK)
    span = blocks.max(axis=(1, 3)).astype(np.int16) - blocks.min(axis=(1, 3))
    return float(np.mean(span <= FLAT_LEVELS))


def red_blue(image: np.ndarray) -> float | None:
    """log(mean red / mean blue) over the lit pixels (every channel within 17..249) of every
    `FLAT_STEP_PX`-th pixel of a BGR or BGRA image; None for a grey image or one with under 100 of them."""
    if image.ndim != 3 or image.shape[2] < 3 or image.dtype != np.uint8:
        return None
    small = image[::FLAT_STEP_PX, ::FLAT_STEP_PX, :3].reshape(-1, 3)
    lit = small[((small > 16) & (small < 250)).all(axis=1)].astype(np.float64)
    if len(lit) < 100:
        return None
    blue, _, red = lit.mean(axis=0)
    return round(float(np.log(red / blue)), 4)


def frame_check(upper: np.ndarray, lower: np.ndarray, repeated: tuple[str, ...] = ()) -> FrameCheckMeta:
    """What a sample's meta records of its two images: how flat each is, whether they are the same,
    `repeated`, the cameras whose frame repeats the one before it (the plan pass's `same_as_before`), and
    each one's `red_blue`."""
    same = upper.shape == lower.shape and bool(np.array_equal(upper, lower))
    return FrameCheckMeta(
        round(flat_fraction(upper), 4), round(flat_fraction(lower), 4), same, list(repeated),
        red_blue(upper), red_blue(lower),
    )  # fmt: skip


@dataclass(frozen=True)
class FrameRecord:
    """What the run-level checks need of one written sample."""

    id: str
    check: FrameCheckMeta | None
    upper: Mapping[str, AlignmentMeta]  # per LiDAR, onto the upper image
    lower: Mapping[str, AlignmentMeta]  # the lower image's quick check
    parts: Mapping[str, list[float | None]] = field(default_factory=dict)  # `SampleMeta.window_parts`
    fit: Mapping[str, list[float | None]] = field(default_factory=dict)  # `SampleMeta.window_fit`
    pair_shift: tuple[float, float] | None = None  # `SampleMeta.stereo_offset`'s shift (px)
    pair_quadrants: tuple[tuple[float, float] | None, ...] = ()  # `SampleMeta.stereo_offset_quadrants`
    range_scatter: Mapping[str, float] = field(default_factory=dict)  # `PointMeta.range_ratio`'s scatter

    @classmethod
    def from_meta(cls, meta: SampleMeta) -> FrameRecord:
        shift = None if meta.stereo_offset is None else (meta.stereo_offset[0], meta.stereo_offset[1])
        quadrants = tuple(None if q is None else (q[0], q[1]) for q in meta.stereo_offset_quadrants)
        scatter = {k: float(v[2]) for k, v in meta.points.range_ratio.items() if len(v) > 2}
        return cls(
            meta.id, meta.frame_check, meta.alignment, meta.lower_check, meta.window_parts, meta.window_fit,
            shift, quadrants, scatter,
        )  # fmt: skip


CAMERAS = ("upper", "lower")


def _off(alignment: Mapping[str, AlignmentMeta]) -> bool:
    """Every LiDAR's alignment moves its points by over `OFF_IMAGE_DEG` and `OFF_IMAGE_PX`."""
    return bool(alignment) and all(
        a.shift_deg > max(OFF_IMAGE_DEG, OFF_IMAGE_PX * a.pixel_deg) for a in alignment.values()
    )


def _aligned(r: FrameRecord, camera: str) -> Mapping[str, AlignmentMeta]:
    return r.upper if camera == "upper" else r.lower


def _flat(r: FrameRecord, camera: str) -> float | None:
    if r.check is None:
        return None
    return r.check.upper_flat if camera == "upper" else r.check.lower_flat


@dataclass(frozen=True)
class FrameFlags:
    """The samples named by each finding (`kind` -> ids, in order) and the run's medians the relative
    tests used (`flat_median`, `correlation_median`, per camera and LiDAR key)."""

    found: dict[str, list[str]]
    samples: int
    flat_median: dict[str, float]
    correlation_median: dict[str, dict[str, float]]
    lower_off_most: list[str] = field(default_factory=list)  # lower images off in most samples: not named
    # here; the stereo pose's check explains them, or `frame_lines.lower_off_line` names them
    pair_shift_median: tuple[float, float] = (0.0, 0.0)  # the run's median `FrameRecord.pair_shift` (px)
    pair_shift_samples: int = 0  # ... over this many samples


def kind(camera: str, what: str) -> str:
    """The summary's flag of a finding (`what`: off, poor, blank; "identical" for both cameras)."""
    if what == "identical":
        return "upper and lower images identical"
    if what == "swapped":
        return "upper and lower images with red and blue swapped against each other"
    if what == "shifted":
        return "upper and lower images shifted against each other"
    return {
        "off": f"{camera} image off every LiDAR's points (> {OFF_IMAGE_DEG:g} deg)",
        "poor": f"{camera} image matching the points far worse than the run's",
        "blank": f"{camera} image blank (one grey level) over much of it",
        "repeat": f"{camera} image repeating the frame before it",
    }[what]


def frame_flags(records: list[FrameRecord]) -> FrameFlags:
    """Each camera's samples that stand out, by the first finding they show (see the module docstring),
    after the samples whose points of one LiDAR alone match far worse (that LiDAR's sweep is out of place,
    which pulls both cameras' checks). The lower images off their points in most samples name none: that
    is the camchain's stereo pose, which the stereo check names."""
    many = len(records) >= MIN_SAMPLES
    found: dict[str, list[str]] = {}
    most: list[str] = []
    identical = [r.id for r in records if r.check is not None and r.check.identical]
    if identical:
        found[kind("", "identical")] = identical
    swapped = [r.id for r in records if r.id not in identical and _swapped(r.check)]
    if swapped:
        found[kind("", "swapped")] = swapped
        identical = identical + swapped  # named once: the other findings leave them out
    flat_median = {c: _median([f for r in records if (f := _flat(r, c)) is not None]) for c in CAMERAS}
    corr_median = {c: _correlations(records, c) for c in CAMERAS}
    apart = _parts_apart(records, set(identical))
    if many:
        named = set(identical).union(*apart.values())
        for what, ids in _lidars_apart(records, corr_median["upper"], named).items():
            apart.setdefault(what, []).extend(ids)
        named = set(identical).union(*apart.values())
        for what, ids in _ranges_apart(records, named).items():
            apart.setdefault(what, []).extend(ids)
    found.update(apart)
    for camera in CAMERAS:
        taken = set(identical).union(*apart.values())
        for what in ("blank", "repeat", "off", "poor"):
            ids = [
                r.id
                for r in records
                if r.id not in taken and _hit(what, r, camera, flat_median, corr_median, many)
            ]
            if ids and _shared(camera, what) and 2 * len(ids) >= len(records):
                most = ids
            elif ids:
                found[kind(camera, what)] = ids
                taken.update(ids)
    shift_median, shifts = _shift_median(records)
    quadrant_medians = _quadrant_medians(records)
    taken = set(identical).union(*found.values())
    shifted = [
        r.id for r in records
        if many and r.id not in taken and _shifted(r, shift_median, quadrant_medians)
    ]  # fmt: skip
    if shifted:
        found[kind("", "shifted")] = shifted
    return FrameFlags(found, len(records), flat_median, corr_median, most, shift_median, shifts)


def _shift_median(records: list[FrameRecord]) -> tuple[tuple[float, float], int]:
    """The run's median pair shift (px, across and along the epipolar lines) and the samples measured."""
    shifts = [r.pair_shift for r in records if r.pair_shift is not None]
    if not shifts:
        return (0.0, 0.0), 0
    dx, dy = np.median(np.asarray(shifts, np.float64), axis=0)
    return (float(dx), float(dy)), len(shifts)


def _quadrant_medians(records: list[FrameRecord]) -> list[tuple[float, float] | None]:
    """Per quadrant of the pairs' GT pixels, the run's median shift (None where no sample measured it)."""
    out: list[tuple[float, float] | None] = []
    for k in range(QUADRANTS):
        found = [q for r in records if len(r.pair_quadrants) == QUADRANTS and (q := r.pair_quadrants[k])]
        out.append(None if not found else (_median([q[0] for q in found]), _median([q[1] for q in found])))
    return out


def _apart(a: tuple[float, float], b: tuple[float, float]) -> float:
    return max(abs(a[0] - b[0]), abs(a[1] - b[1]))


def _shifted(
    r: FrameRecord, median: tuple[float, float], quadrant_medians: list[tuple[float, float] | None]
) -> bool:
    """The pair's shift differs from the run's median by over `PAIR_SHIFT_PX` across or along the lines,
    or one quadrant's from the run's median of that quadrant by over `PAIR_QUADRANT_PX`."""
    if r.pair_shift is None:
        return False
    if _apart(r.pair_shift, median) > PAIR_SHIFT_PX:
        return True
    return any(
        q is not None and m is not None and _apart(q, m) > PAIR_QUADRANT_PX
        for q, m in zip(r.pair_quadrants, quadrant_medians, strict=False)
    )


def _swapped(check: FrameCheckMeta | None) -> bool:
    """The two images' colour balances differ by over `SWAP_MIN` and are each other's negative (within
    `SWAP_LEFT` of that difference): one camera's red and blue are the other order."""
    if check is None or check.upper_red_blue is None or check.lower_red_blue is None:
        return False
    upper, lower = check.upper_red_blue, check.lower_red_blue
    apart = abs(upper - lower)
    return apart > SWAP_MIN and abs(upper + lower) < SWAP_LEFT * apart


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else 0.0


def _correlations(records: list[FrameRecord], camera: str) -> dict[str, float]:
    """Per alignment key (LiDAR) of `camera`, the median correlation over the samples."""
    keys = {k for r in records for k in _aligned(r, camera)}
    return {k: _median([a.correlation for r in records if (a := _aligned(r, camera).get(k))]) for k in keys}


def _hit(
    what: str, r: FrameRecord, camera: str, flat_median: Mapping[str, float],
    corr_median: Mapping[str, Mapping[str, float]], many: bool,
) -> bool:  # fmt: skip
    """Whether sample `r`'s `camera` image shows finding `what`."""
    if what == "blank":
        return _blank(_flat(r, camera), flat_median[camera], many)
    if what == "repeat":
        return r.check is not None and camera in r.check.repeated
    if what == "off":
        return _off(_aligned(r, camera))
    return many and _poor(_aligned(r, camera), corr_median[camera])


def _lidars_apart(
    records: list[FrameRecord], medians: Mapping[str, float], named: set[str]
) -> dict[str, list[str]]:
    """Per LiDAR, the samples not `named` yet whose points of it alone match the upper image far worse
    than the run's (`POOR_MATCH`): a sweep out of place (another unit's points, an axis flipped)."""
    found: dict[str, list[str]] = {}
    for r in records:
        if r.id in named or len(r.upper) < 2:
            continue
        poor = [k for k, a in sorted(r.upper.items()) if _poor({k: a}, medians)]
        if len(poor) < len(r.upper):  # every LiDAR's: the image's fault, found as such
            for k in poor:
                found.setdefault(lidar_kind(k), []).append(r.id)
    return found


def _ranges_apart(records: list[FrameRecord], named: set[str]) -> dict[str, list[str]]:
    """Per LiDAR after the rig's first, the samples not `named` yet whose ranges scatter against the first
    LiDAR's (`range_scatter`) by over `SCATTER_OUT` times the run's median and `SCATTER_MIN`: in that
    window one of the two LiDARs' points land apart from where the other's say the surfaces are (a sweep
    turned or moved by a little, which its own stretches and the image cannot tell)."""
    found: dict[str, list[str]] = {}
    for lidar in sorted({k for r in records for k in r.range_scatter}):
        median = _median([r.range_scatter[lidar] for r in records if lidar in r.range_scatter])
        bound = max(SCATTER_OUT * median, SCATTER_MIN)
        for r in records:
            if r.id not in named and r.range_scatter.get(lidar, 0.0) > bound:
                found.setdefault(scatter_kind(lidar), []).append(r.id)
    return found


def scatter_kind(lidar: str) -> str:
    """The summary's flag of a sample whose `lidar`'s ranges scatter against the first LiDAR's."""
    return f"{lidar}'s ranges scattering against the first LiDAR's far more than in the run's other samples"


def _parts_apart(records: list[FrameRecord], named: set[str]) -> dict[str, list[str]]:
    """Per LiDAR, the samples not `named` yet with a stretch of its window out of place (`_part_out`); by
    the image only where the image does not lie off every LiDAR's points (`_off`: the frame's fault, named
    as such)."""
    found: dict[str, list[str]] = {}
    for r in records:
        if r.id in named:
            continue
        image_off = _off(r.upper)  # the image lies off every LiDAR: its stretches' matches say nothing
        for lidar in sorted({*r.parts, *r.fit}):
            by_image = not image_off and _part_out(r.parts.get(lidar, []), PART_MATCH, MIN_MEDIAN)
            if by_image or _part_out(r.fit.get(lidar, []), FIT_MATCH, MIN_FIT):
                found.setdefault(part_kind(lidar), []).append(r.id)
    return found


def _part_out(parts: list[float | None], ratio: float, least: float) -> bool:
    """A stretch's measure is below `ratio` of the window's median stretch's, which is above `least` (it
    measures something); at least `MIN_PARTS` stretches measured."""
    judged = [c for c in parts if c is not None]
    median = _median(judged)
    return len(judged) >= MIN_PARTS and median > least and min(judged) < ratio * median


def part_kind(lidar: str) -> str:
    """The summary's flag of a sample with a stretch of `lidar`'s window out of place (`_part_out`)."""
    return f"{lidar}'s points in a stretch of the window out of place against the rest"


def lidar_kind(lidar: str) -> str:
    """The summary's flag of a sample whose points of `lidar` alone match the upper image far worse."""
    return f"{lidar}'s points matching the upper image far worse than the run's"


def _shared(camera: str, what: str) -> bool:
    """Findings that most samples sharing is not a frame out of place: lower images off their points (the
    camchain's stereo pose)."""
    return camera == "lower" and what == "off"


def _blank(flat: float | None, median: float, many: bool) -> bool:
    """Flat over `FLAT_ALL` of the image, or (`many` samples) `FLAT_MORE` beyond the run's median."""
    return flat is not None and (flat >= FLAT_ALL or (many and flat > median + FLAT_MORE))


def _poor(aligned: Mapping[str, AlignmentMeta], medians: Mapping[str, float]) -> bool:
    """Every LiDAR's correlation below `POOR_MATCH` of its run median (a median under `MIN_MEDIAN` gives
    no measure). A sample without alignment is not judged: a LiDAR silent in its window leaves it out, and
    a blank image, which gives none, is found as blank."""
    return bool(aligned) and all(
        (m := medians.get(k, 0.0)) > MIN_MEDIAN and a.correlation < POOR_MATCH * m for k, a in aligned.items()
    )
