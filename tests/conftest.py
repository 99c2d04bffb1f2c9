"""Test-session settings: caches (catalog, pattern databases) go to a temporary folder, never the user's."""

import pytest


@pytest.fixture(autouse=True, scope="session")
def session_cache_dir(tmp_path_factory):
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STARENV_CACHE_DIR", str(tmp_path_factory.mktemp("starenv-cache")))
        yield
