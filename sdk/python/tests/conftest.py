"""Fixtures: a live `kairos serve` in a temporary data directory (live_server.py)."""

import pytest

from live_server import Server


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """One server for the session's tests (the restart test restarts it in place)."""
    server = Server(tmp_path_factory.mktemp("kairos") / "kairos-data")
    server.start()
    yield server
    server.stop()
