"""Issue 49 (F17): a dataset.yaml cut short is named as cut at its last line, not as a dataset made otherwise.

YAML cut at a line end still parses: a file cut inside `R_cam0_rect` made a
rerun say the dataset was "made with a different 'R_cam0_rect'" and `stats`
say "fisheye_size: expected [height, width] in px, got None". Both must say
the file is truncated at the line it ends at, and what it ends before.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from ingest.dataset.description import SOURCE_KEYS, TOP_KEYS
from ingest.errors import DatasetError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from tests.faults.bags import INDOOR
from tests.faults.cli import sensorbox

RIG = INDOOR.parent / "indoor_static_mcap.truth" / "rig.yaml"
FAST = {"workers": 1, "every": 3, "height_full": 64, "gt": "sparse"}


def _cut_after(path: Path, lines: int) -> None:
    kept = path.read_text().splitlines(keepends=True)[:lines]
    path.write_text("".join(kept))


def test_a_dataset_yaml_cut_at_a_line_end_is_named_truncated_at_that_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "ds"
    ingest([INDOOR], IngestConfig(rig=RIG, out=out, **FAST))  # type: ignore[arg-type]
    path = out / "dataset.yaml"
    whole = path.read_text()
    doc = yaml.safe_load(whole)
    assert tuple(doc) == TOP_KEYS  # what the check expects is what ingest writes, in its order
    assert tuple(doc["sources"][0])[: len(SOURCE_KEYS)] == SOURCE_KEYS
    lines = whole.splitlines()
    in_rect = lines.index("R_cam0_rect:") + 4  # its first row and one value of the second
    in_source = next(i for i, line in enumerate(lines) if line.startswith("  paths:")) + 2
    advice = (
        "which ingest writes; delete it (a rerun of ingest checks the samples against their meta and writes "
        "it anew) or restore it"
    )
    for cut, before in ((in_rect, "'R_cam1_rect'"), (in_source, "source 1's 'ground_truth'")):
        path.write_text(whole)
        _cut_after(path, cut)
        line = (
            f"{path}: truncated or unreadable at line {cut}: the file ends there, before {before}, {advice}"
        )
        with pytest.raises(DatasetError) as err:
            ingest([INDOOR], IngestConfig(rig=RIG, out=out, **FAST))  # type: ignore[arg-type]
        assert str(err.value) == line
        code, _, stderr = sensorbox(capsys, "stats", str(out))
        assert (code, stderr) == (2, [f"error: {line}"])
        assert not (out / "stats.json").exists()
    path.write_text(whole)  # whole again: resumed, every sample already done
    assert ingest([INDOOR], IngestConfig(rig=RIG, out=out, **FAST)).resumed == 7  # type: ignore[arg-type]


def test_a_dataset_yaml_listing_a_recording_twice_or_overlapping_ids_is_refused(tmp_path: Path) -> None:
    """Sweep 7 S7: dataset.yaml whose `sources` listed its one source twice, the copy at first_id 5, was
    resumed ('0 / 5') and written back, describing 10 samples of which 5 exist."""
    out = tmp_path / "ds"
    ingest([INDOOR], IngestConfig(rig=RIG, out=out, **FAST))  # type: ignore[arg-type]
    path = out / "dataset.yaml"
    whole = path.read_text()
    doc = yaml.safe_load(whole)
    source = doc["sources"][0]
    advice = (
        "not what ingest writes; delete it (a rerun of ingest checks the samples against their meta and writes it "
        "anew) or restore it"
    )
    overlap = {**source, "bags": ["other.mcap"], "first_id": 3}
    for extra, clash in (
        (
            {**source, "first_id": source["samples"]},
            "sources[1] lists the bags of sources[0] again (indoor_static_mcap)",
        ),
        (overlap, "sources[1]'s samples 3..9 overlap sources[0]'s 0..6"),
    ):
        path.write_text(yaml.safe_dump({**doc, "sources": [source, extra]}, sort_keys=False))
        with pytest.raises(DatasetError) as err:
            ingest([INDOOR], IngestConfig(rig=RIG, out=out, **FAST))  # type: ignore[arg-type]
        assert str(err.value) == f"{path}: {clash}: {advice}"
    path.unlink()  # deleted: the rerun checks the samples against their meta and writes it anew
    again = ingest([INDOOR], IngestConfig(rig=RIG, out=out, **FAST))  # type: ignore[arg-type]
    assert again.resumed == 7 and len(yaml.safe_load(path.read_text())["sources"]) == 1
