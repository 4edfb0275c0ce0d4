"""Shared test set-up: PSF caches go to a per-session temporary folder, never the user's."""

import pytest


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    import os

    os.environ["BMI_CACHE_DIR"] = str(tmp_path_factory.mktemp("bmi_cache"))
    yield
