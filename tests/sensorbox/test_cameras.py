"""Camera sources and stereo pairing: a video file through OpenCV, the ZED API against a stand-in
module (and its absence), the simulated cameras against the simulator's own fixture bag, and the
camera node's pairing, encoding and topics."""

from __future__ import annotations

import sys
import threading
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from ingest.bags.decode import decode_compressed_image, decode_image
from ingest.bags.reader import open_bags
from sensorbox.errors import DriverError
from sensorbox.live.cameras import CameraNode, CameraOutput, Frame, StereoPairer
from sensorbox.live.sources import OpenCVSource, ZedSource, _count_gap
from sensorbox.sim.camera_source import SimCameras, SimCameraSource
from sensorbox.sim.fixtures import FIXTURES, fixture_bag
from tests.cpu_bounds import RAW_PIXEL_LEVELS
from tests.live import ManualClock, wait_for
from tests.paths import FIXTURES_DIR

UPPER = "/zed_upper/zed_node/rgb/color/rect/image"
LOWER = "/zed_lower/zed_node/rgb/color/rect/image"


# ---------------------------------------------------------------- pairing


def test_pairer_pairs_nearest_and_counts_unpaired():
    p = StereoPairer(tolerance_ns=10)
    out = []
    for cam, stamp in [(0, 0), (1, 1), (0, 33), (0, 66), (1, 67), (1, 99), (0, 100), (1, 140)]:
        out += p.push(cam, stamp, stamp)
    assert out == [(0, 1), (66, 67), (100, 99)]
    assert p.pairs == 3 and p.unpaired == [1, 0] and p.max_abs_dt_ns == 1
    p.flush()  # 140 still waits for an upper frame: the stream stopped first, not a drop
    assert p.unpaired == [1, 0] and p.at_stop == [0, 1]
    assert p.push(0, 141, 141) == []  # forgotten: 141 does not pair with 140


def test_pairer_ages_out_frames_of_a_silent_partner():
    p = StereoPairer(tolerance_ns=5, max_pending=2)
    for k in range(5):
        assert p.push(0, k * 33, k) == []
    assert p.unpaired == [3, 0]  # only the newest two wait: 99 and 132
    assert p.push(1, 134, "x") == [(4, "x")]  # 99 can never pair with 134 or later; 132 does
    assert p.unpaired == [4, 0] and p.pairs == 1


def test_unpaired_frames_of_both_cameras_add_up_in_the_nodes_pair_drops():
    """A lower frame that can never pair counts for the lower camera (unpaired[1]), and the node's "pair"
    drop is both cameras' sum: upper 0 (lower 100 came next), lower 100 (upper 300 next) and lower 400
    (upper 500 next) make unpaired [1, 2] and 3 pair drops; 300 and 305 pair."""
    node = CameraNode(
        "stereo", [ListSource("upper", []), ListSource("lower", [])],
        [CameraOutput(UPPER, "cam0_optical_frame"), CameraOutput(LOWER, "cam1_optical_frame")],
        lambda *m: None, image="jpeg", pair_tolerance_ns=10,
    )  # fmt: skip
    p = node.pairer
    assert p is not None
    out = []
    for cam, stamp in [(0, 0), (1, 100), (0, 300), (1, 305), (1, 400), (0, 500)]:
        out += p.push(cam, stamp, stamp)
    assert out == [(300, 305)] and p.unpaired == [1, 2]
    assert node.status().drops["pair"] == 3


# ---------------------------------------------------------------- OpenCV


def write_video(path: Path, n: int, fps: float = 10.0) -> list[np.ndarray]:
    frames = []
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (64, 48))
    assert writer.isOpened()
    for k in range(n):
        img = np.full((48, 64, 3), (20 * k, 100, 200 - 10 * k), np.uint8)
        writer.write(img)
        frames.append(img)
    writer.release()
    return frames


def test_opencv_source_reads_a_video_file_with_file_stamps(tmp_path):
    video = tmp_path / "cam.avi"
    sent = write_video(video, 12, fps=10.0)
    src = OpenCVSource(str(video), start_ns=1_000_000_000)
    src.open()
    stop = threading.Event()
    got = []
    while (f := src.read(stop)) is not None:
        got.append(f)
    src.close()
    assert len(got) == 12 and src.frames == 12 and src.dropped == 0
    assert [f.stamp_ns for f in got] == [1_000_000_000 + k * 100_000_000 for k in range(12)]
    assert [f.seq for f in got] == list(range(12))
    for f, img in zip(got, sent, strict=True):
        assert f.bgr.shape == (48, 64, 3) and f.bgr.dtype == np.uint8
        assert np.abs(f.bgr.astype(int) - img).mean() < 3  # MJPG is lossy


def test_opencv_source_errors(tmp_path):
    with pytest.raises(DriverError, match="no such device or video file"):
        OpenCVSource(str(tmp_path / "missing.avi")).open()
    (tmp_path / "junk.avi").write_bytes(b"not a video")
    with pytest.raises(DriverError, match="cannot open"):
        OpenCVSource(str(tmp_path / "junk.avi")).open()
    with pytest.raises(DriverError, match="before open"):
        OpenCVSource("/dev/video0").read(threading.Event())


# ---------------------------------------------------------------- ZED


def test_a_dropped_frame_is_counted_despite_stamp_jitter():
    """Frames missing between two stamps of a 30 Hz camera: the gap in periods, rounded, less one; a
    frame dropped between stamps that came a little early (66 ms: 1.98 periods) is still one."""
    period = 1e9 / 30
    assert _count_gap(None, 66_000_000, period) == 0  # the first frame
    assert _count_gap(0, 34_000_000, period) == 0  # 1.02 periods: the next frame, late
    assert _count_gap(0, 32_000_000, period) == 0  # 0.96 periods: the next frame, early
    assert _count_gap(0, 66_000_000, period) == 1  # 1.98 periods
    assert _count_gap(0, 101_000_000, period) == 2  # 3.03 periods
    assert _count_gap(0, 132_000_000, period) == 3  # 3.96 periods
    assert _count_gap(0, 66_000_000, 0.0) == 0  # no frame rate known


def test_zed_without_pyzed_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyzed", None)
    monkeypatch.setitem(sys.modules, "pyzed.sl", None)
    with pytest.raises(DriverError, match=r"pyzed.*not installed.*'opencv'"):
        ZedSource(serial=123).open()


def fake_pyzed(frames: list[tuple[int, np.ndarray]], opened: dict[str, object]) -> types.ModuleType:
    """The parts of `pyzed.sl` ZedSource uses, as the ZED SDK's ZED One sample calls them."""
    sl = types.ModuleType("pyzed.sl")

    class ERROR_CODE:  # noqa: N801 - the SDK's names
        SUCCESS = 0
        END_OF_SVOFILE_REACHED = 3

    class RESOLUTION:
        HD1200 = "HD1200"

    class TIME_REFERENCE:  # noqa: N801
        IMAGE = "image"

    class InitParametersOne:
        def __init__(self):
            self.camera_resolution = None
            self.camera_fps = 0
            self.serial = None

        def set_from_serial_number(self, serial):
            self.serial = serial

    class Mat:
        data = None

        def get_data(self):
            return self.data

    class Timestamp:
        def __init__(self, ns):
            self.ns = ns

        def get_nanoseconds(self):
            return self.ns

    class CameraOne:
        def __init__(self):
            self.k = -1

        def open(self, init):
            opened.update(resolution=init.camera_resolution, fps=init.camera_fps, serial=init.serial)
            return ERROR_CODE.SUCCESS

        def grab(self):
            self.k += 1
            return ERROR_CODE.SUCCESS if self.k < len(frames) else ERROR_CODE.END_OF_SVOFILE_REACHED

        def retrieve_image(self, mat):
            mat.data = frames[self.k][1]

        def get_timestamp(self, ref):
            assert ref == TIME_REFERENCE.IMAGE
            return Timestamp(frames[self.k][0])

        def close(self):
            opened["closed"] = True

    for obj in (ERROR_CODE, RESOLUTION, TIME_REFERENCE, InitParametersOne, Mat, CameraOne):
        setattr(sl, obj.__name__, obj)
    return sl


def test_zed_source_against_the_sdk_api(monkeypatch):
    period = 1e9 / 30
    stamps = [5_000_000_000 + round(k * period) for k in (0, 1, 3, 4)]  # frame 2 missing
    bgra = [np.dstack([np.full((4, 6), v, np.uint8) for v in (k, 50 + k, 100 + k, 255)]) for k in range(4)]
    opened: dict[str, object] = {}
    sl = fake_pyzed(list(zip(stamps, bgra, strict=True)), opened)
    pkg = types.ModuleType("pyzed")
    pkg.sl = sl  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "pyzed", pkg)
    monkeypatch.setitem(sys.modules, "pyzed.sl", sl)
    src = ZedSource(serial=301234, fps=30)
    src.open()
    assert opened == {"resolution": "HD1200", "fps": 30, "serial": 301234}
    frames = [src.read(threading.Event()) for _ in range(4)]
    assert [f.stamp_ns for f in frames if f] == stamps
    assert all(f is not None and f.bgr.shape == (4, 6, 3) for f in frames)
    assert [tuple(f.bgr[0, 0]) for f in frames if f] == [(k, 50 + k, 100 + k) for k in range(4)]
    assert src.dropped == 1
    with pytest.raises(DriverError, match="grab failed 30 times"):
        src.read(threading.Event())
    src.close()
    assert opened["closed"]


# ---------------------------------------------------------------- simulator


def test_sim_cameras_reproduce_the_simulators_frames_and_stamps():
    cfg = FIXTURES["outdoor_walk_mcap"]  # raw bgra8 images of a walk: poses change every frame
    sim = SimCameras(cfg)
    with open_bags(fixture_bag("outdoor_walk_mcap", FIXTURES_DIR)) as bags:
        msgs = {t: [m for m in bags.messages([t])][:3] for t in (UPPER, LOWER)}
    for cam, topic in enumerate((UPPER, LOWER)):
        assert sim.topic(cam) == topic
        for k, m in enumerate(msgs[topic]):
            frame = decode_image(m.raw)
            assert frame.stamp_ns == sim.stamp_ns(k, cam)
            # the fixture's CPU may have rendered through other SIMD paths (tests/cpu_bounds.py)
            diff = np.abs(sim.render(k, cam).astype(np.int16) - frame.image)
            assert diff.max() <= RAW_PIXEL_LEVELS and (diff > 0).mean() < 1e-3, (
                topic,
                k,
                int(diff.max()),
                float((diff > 0).mean()),
            )


@pytest.mark.realtime
def test_sim_camera_source_paces_and_counts_skipped_frames():
    sim = SimCameras(FIXTURES["indoor_static_mcap"])
    clock = ManualClock(1000.0)
    src = SimCameraSource(sim, 1, prerender="always", buffer_frames=4, clock=clock)
    src.open()
    assert len(src.loop) == 1  # static: every frame is the same image
    src.start_clock(clock() - 1.0)  # one second behind: frames 0..29 made, the ring keeps 26..29
    stop = threading.Event()
    first = src.read(stop)
    assert first is not None and src.dropped == 26 and first.seq == 26
    second = src.read(stop)
    assert second is not None and second.seq == first.seq + 1
    assert [first.stamp_ns, second.stamp_ns] == [sim.stamp_ns(first.seq, 1), sim.stamp_ns(second.seq, 1)]
    np.testing.assert_array_equal(first.bgr, sim.render(0, 1))


def test_sim_rig_written_at_render_resolution(tmp_path):
    sim = SimCameras(FIXTURES["indoor_static_mcap"])
    path = sim.write_rig(tmp_path / "rig.yaml")
    from calibration.rig import read_rig

    rig = read_rig(path)
    assert (rig.upper.model.width, rig.upper.model.height) == (480, 300)
    assert [p.name for p in sorted(tmp_path.iterdir())] == ["rig-camchain.yaml", "rig.yaml"]


# ---------------------------------------------------------------- the camera node


class ListSource:
    def __init__(self, name, frames):
        self.name, self.frames_in, self.frames, self.dropped = name, list(frames), 0, 0

    def open(self):
        pass

    def read(self, stop):
        if not self.frames_in:
            return None
        self.frames += 1
        return self.frames_in.pop(0)

    def close(self):
        pass


@pytest.mark.realtime
def test_stereo_node_publishes_pairs_only_as_jpeg():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (60, 80, 3), dtype=np.uint8), (7, 7), 2).astype(np.uint8)
    upper = [Frame(s, img, k) for k, s in enumerate([0, 33_000_000, 66_000_000])]
    lower = [Frame(s, img[::-1].copy(), k) for k, s in enumerate([100_000, 66_200_000, 99_000_000])]
    got = []
    lock = threading.Lock()

    def publish(*m):
        with lock:
            got.append(m)

    node = CameraNode(
        "stereo", [ListSource("upper", upper), ListSource("lower", lower)],
        [CameraOutput(UPPER, "cam0_optical_frame"), CameraOutput(LOWER, "cam1_optical_frame")],
        publish, image="jpeg", jpeg_quality=95, pair_tolerance_ns=16_000_000,
    )  # fmt: skip
    node.start()
    wait_for(lambda: node.done, "the sources to finish")
    node.stop()
    assert [(t, s) for t, _, s, _ in got] == [
        (UPPER + "/compressed", 0), (LOWER + "/compressed", 100_000),
        (UPPER + "/compressed", 66_000_000), (LOWER + "/compressed", 66_200_000),
    ]  # fmt: skip
    decoded = decode_compressed_image(got[2][3])
    assert decoded.frame_id == "cam0_optical_frame" and decoded.stamp_ns == 66_000_000
    _, ref = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    np.testing.assert_array_equal(decoded.image, cv2.imdecode(ref, cv2.IMREAD_COLOR))  # quality 95 applied
    st = node.status()
    assert st.drops == {"source": 0, "encode": 0, "pair": 1}  # upper 33 ms: lower 66.2 came next
    assert st.counters["pairs"] == 2 and st.counters["pair_max_dt_ms"] == pytest.approx(0.2)
    assert st.counters["unpaired_at_stop"] == 1  # lower 99 ms, still waiting when the node stopped


@pytest.mark.realtime
def test_camera_node_raw_images_keep_every_frame():
    img = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)
    got = []
    node = CameraNode("cam", [ListSource("c", [Frame(k, img, k) for k in range(3)])],
                      [CameraOutput("/cam/image", "f")], lambda *m: got.append(m), image="raw")  # fmt: skip
    node.start()
    wait_for(lambda: node.done, "the sources to finish")
    node.stop()
    assert [(t, s) for t, _, s, _ in got] == [("/cam/image", 0), ("/cam/image", 1), ("/cam/image", 2)]
    np.testing.assert_array_equal(decode_image(got[1][3]).image, img)
    with pytest.raises(DriverError, match="stereo pairing needs two sources"):
        CameraNode("x", [ListSource("c", [])], [CameraOutput("/a", "f")], print, pair_tolerance_ns=1)
