"""Fixtures of the workbench tests: a headless Debian chromium driven by playwright."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.app._server import store_finished_jobs

CHROMIUM = Path("/usr/bin/chromium")
"""Debian's chromium (scripts/setup.sh installs it); playwright drives it instead of its own download."""
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--disable-quic",
                 "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync"]
"""Software WebGL (SwiftShader) for viser's canvas; no network traffic of its own."""

needs_chromium = pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian chromium is not installed (scripts/setup.sh)")


@pytest.fixture(scope="module")
def chromium():
    """A headless chromium (playwright ``Browser``), one per test module; closed after it."""
    if not CHROMIUM.exists():
        pytest.skip("Debian chromium is not installed (scripts/setup.sh)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
        try:
            yield browser
        finally:
            browser.close()


@pytest.fixture(scope="module")
def replayed(small_session, tmp_path_factory):
    """A data directory whose database holds the `small` session and its finished replay
    job 1 (seq01), written as the replay job writes it (``write_replay`` and the viewer's
    arrays) and stored as the runner stores a finished job: the browser tests need no Dask job."""
    from app.server.jobs.types import ReplayParams
    from app.viewer.data import write_viewer_arrays
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig, replay, write_replay

    data = tmp_path_factory.mktemp("replayed") / "data"
    folder = (data / "jobs" / "1").resolve()
    config = ReplayConfig(sequences=("seq01",))
    prepared = prepare_session(small_session, config)
    result = replay(small_session, config, prepared=prepared)
    write_replay(result, folder)
    write_viewer_arrays(prepared, result, folder)
    summary = {**result.to_json(), "viewer": True}
    store_finished_jobs(data, small_session, "small",
                        [(1, "replay", ReplayParams(session_id=1, sequences=["seq01"]), summary, folder)])
    return data
