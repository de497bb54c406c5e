"""Paths into this checkout that the tests read: the repository root and the fixture bags."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURES_DIR = ROOT / "tests" / "fixtures"
