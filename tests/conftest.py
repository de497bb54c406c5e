"""Session-wide test settings."""

from __future__ import annotations

import os

import pytest

from calibration.warp import MAP_CACHE_ENV


@pytest.fixture(autouse=True, scope="session")
def _map_cache_in_a_temporary_folder(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Remap maps cached on disk go to the session's temporary folder, never the user's ~/.cache."""
    os.environ[MAP_CACHE_ENV] = str(tmp_path_factory.mktemp("map_cache"))
