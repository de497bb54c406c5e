"""Atomic writes of dataset files."""

import stat

from ingest.dataset.layout import write_atomic


def test_written_files_are_readable_by_others_and_no_temporary_is_left(tmp_path):
    path = tmp_path / "000000.png"
    write_atomic(path, b"abc")
    assert path.read_bytes() == b"abc"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["000000.png"]
