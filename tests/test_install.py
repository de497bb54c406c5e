"""A non-editable install finds what it ships (reference rig, launch files) in the package, not in this checkout.

The wheel is built from this checkout and installed into a fresh virtual environment; its
dependencies come from the test's own environment (a path entry, so the editable install of
this checkout there is not picked up). The commands run from a folder outside the checkout.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

from tests.paths import ROOT


def _run(*args: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    res = subprocess.run([str(a) for a in args], capture_output=True, text=True, cwd=cwd, check=False)
    assert res.returncode == 0, f"{args}: {res.stdout}\n{res.stderr}"
    return res


def _source_copy(dst: Path) -> Path:
    """What a wheel is built from (packages, pyproject, README), so the build leaves this checkout alone."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("calibration", "ingest", "sensorbox"):
        shutil.copytree(ROOT / name, dst / name, symlinks=True, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dst / name)
    return dst


def test_an_installed_wheel_runs_launch_and_calib_check_outside_the_checkout(tmp_path):
    wheels, venv, elsewhere = tmp_path / "wheels", tmp_path / "venv", tmp_path / "elsewhere"
    elsewhere.mkdir()
    source = _source_copy(tmp_path / "source")
    _run(sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", wheels, source, cwd=elsewhere)
    _run(sys.executable, "-m", "venv", venv, cwd=elsewhere)
    python = venv / "bin" / "python"
    site = Path(_run(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])", cwd=elsewhere)
                .stdout.strip())  # fmt: skip
    (site / "sensorbox-test-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    (wheel,) = wheels.glob("sensorbox-*.whl")
    _run(python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", wheel, cwd=elsewhere)

    where = _run(python, "-c", "import sensorbox, calibration.rig as r; print(sensorbox.__file__); print(r.REFERENCE_RIG)",
                 cwd=elsewhere).stdout.split()  # fmt: skip
    assert all(Path(p).is_relative_to(site) for p in where), where
    share = site / "sensorbox" / "share"
    launch = _run(
        venv / "bin" / "sensorbox", "launch", share / "launch" / "sim.launch.yaml", "--dry-run", cwd=elsewhere
    )
    assert f"    param rig = '{share / 'calibration' / 'sensorbox.yaml'}'\n" in launch.stdout
    assert (share / "calibration" / "sensorbox.yaml").is_file() and not (share / "calibration").is_symlink()
    check = _run(venv / "bin" / "sensorbox", "calib", "check", where[1], cwd=elsewhere)
    assert "cam0" in check.stdout and str(ROOT) not in launch.stdout + check.stdout
