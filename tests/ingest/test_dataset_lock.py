"""One run per output folder; a killed run's temporaries are removed by the next (`ingest.dataset.lock`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from ingest.dataset.layout import write_atomic
from ingest.dataset.lock import hold_folder
from ingest.errors import DatasetError, OdometryError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from tests.ingest.test_pipeline import INDOOR, _rig

KILLED = (".000001.png.k3x_9QzA.tmp", "left_fisheye")  # write_atomic's name for left_fisheye/000001.png


def test_a_held_folder_is_refused_and_released_when_its_holder_dies(tmp_path: Path) -> None:
    with hold_folder(tmp_path) as removed:
        assert removed == 0
        busy = rf"^{tmp_path}: another SensorBox run is writing into this folder"
        with pytest.raises(DatasetError, match=busy), hold_folder(tmp_path):
            pass
    with hold_folder(tmp_path):  # released on exit
        pass
    holder = subprocess.Popen(  # another process holds it, then is killed: the kernel releases the lock
        [sys.executable, "-c", "import sys, time; from pathlib import Path; from ingest.dataset.lock import "
         "hold_folder\nwith hold_folder(Path(sys.argv[1])):\n    print('held', flush=True); time.sleep(60)",
         str(tmp_path)], stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        with pytest.raises(DatasetError, match="another SensorBox run"), hold_folder(tmp_path):
            pass
    finally:
        holder.kill()
        holder.wait()
    with hold_folder(tmp_path):
        pass


def test_a_rerun_removes_the_temporaries_of_a_killed_run_and_nothing_else(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    first = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    name, folder = KILLED
    (out / folder / name).write_bytes(b"half a png")
    (out / ".rig.a1b2c3d4.tmp").mkdir()  # describe's staging folder for rig/
    (out / ".rig.a1b2c3d4.tmp" / "rig.yaml").write_text("half")
    (out / "notes.tmp").write_text("mine")  # not a temporary of ours: stays
    (out / ".mine.tmp").write_text("mine")
    again = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    assert (again.written, again.resumed, again.stale_temporaries) == (0, first.written, 2)
    after = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == {**before, out / "notes.tmp": b"mine", out / ".mine.tmp": b"mine"}


@pytest.mark.parametrize("gt", ["sparse", "dense"])
def test_a_second_run_into_a_held_dataset_is_refused_before_it_writes(tmp_path: Path, gt: str) -> None:
    """Refused before its first write: the dense run's trajectory file and the sample folders too."""
    out = tmp_path / "ds"
    out.mkdir()
    write_atomic(out / "mine.txt", b"x")
    with (
        hold_folder(out),
        pytest.raises(DatasetError, match="another SensorBox run is writing into this folder"),
    ):
        ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10, gt=gt))
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


def test_a_run_refused_after_creating_the_output_removes_it_again(tmp_path: Path) -> None:
    """--gt dense on a recording with 100 ms of LiDAR, too short for a trajectory: the folder made for
    the lock goes again, and the error names the recording."""
    from tests.faults.bags import LIDAR_BOTTOM, LIDAR_TOP, rewrite

    def first_sweeps(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic in (LIDAR_TOP, LIDAR_BOTTOM) and k > 0 else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", first_sweeps)
    out = tmp_path / "ds"
    with pytest.raises(
        OdometryError, match=rf"^{bag}: odometry: less than 200 ms of LiDAR points \(\d+ ms\); "
    ):
        ingest([bag], IngestConfig(rig=rig, out=out, workers=1, gt="dense"))
    assert not out.exists()


def test_a_file_system_without_locks_runs_unlocked_and_says_so(tmp_path, monkeypatch, caplog) -> None:
    """Some network mounts refuse flock (ENOLCK): the run goes on with a warning, and leaves temporaries
    alone (one could be another run's)."""
    import errno
    import fcntl

    def refuse(fd: int, op: int) -> None:
        raise OSError(errno.ENOLCK, "No locks available")

    (tmp_path / KILLED[0]).write_bytes(b"x")
    monkeypatch.setattr(fcntl, "flock", refuse)
    with caplog.at_level("WARNING"), hold_folder(tmp_path) as removed:
        assert removed == 0
    assert (tmp_path / KILLED[0]).exists()
    assert f"cannot lock {tmp_path} (No locks available)" in caplog.text


def test_the_unlocked_warning_is_a_warning_line_of_the_cli(tmp_path: Path) -> None:
    """A library warning (here: the folder cannot be locked) prints as the CLI's "warning: ..." line."""
    code = (
        "import errno, fcntl, sys\n"
        "def refuse(fd, op): raise OSError(errno.ENOLCK, 'No locks available')\n"
        "fcntl.flock = refuse\n"
        "from sensorbox.cli.main import main\n"
        "sys.argv = ['sensorbox', 'ingest', sys.argv[1], '--rig', sys.argv[2], '--out', sys.argv[3],\n"
        "            '--workers', '1', '--every', '10', '--no-preview', '--gt', 'sparse']\n"
        "main()\n"
    )
    out = tmp_path / "ds"
    res = subprocess.run(
        [sys.executable, "-c", code, str(INDOOR), str(_rig(INDOOR)), str(out)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stderr.splitlines() == [
        f"warning: cannot lock {out} (No locks available): a second run into it would not be refused"
    ]
