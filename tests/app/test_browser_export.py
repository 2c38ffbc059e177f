"""The dashboard's export links (issue 19, item 5) in a real headless browser (Debian
chromium + playwright): a finished replay job shows "VTU", "SOFA" and "MJCF" links to
``/api/jobs/{id}/export`` in the job list and in its result panel, and one downloads.

The finished replay job comes from the ``replayed`` fixture (tests/app/conftest.py): no
Dask job; the server then serves the real export.
"""

from __future__ import annotations

import zipfile

import pytest

from tests.app._server import Server
from tests.app.conftest import needs_chromium

pytestmark = [pytest.mark.slow, needs_chromium]


def test_export_links_of_a_finished_replay_in_chromium(replayed, chromium, tmp_path):
    server = Server(replayed)
    try:
        page = chromium.new_page(viewport={"width": 1400, "height": 1100}, accept_downloads=True)
        try:
            page.goto(server.url + "/")
            page.wait_for_selector("body[data-ready='1']")
            row = "#jobs-table tr[data-job-id='1'][data-status='done']"
            page.wait_for_selector(f"{row} a.export-link")
            for where in (row, "#export-links"):  # the job list, and the result panel (it follows the latest job)
                page.wait_for_selector(f"{where} a.export-link")
                links = page.locator(f"{where} a.export-link")
                assert links.all_inner_texts() == ["VTU", "SOFA", "MJCF"]
                for i, fmt in enumerate(("vtu", "sofa", "mjcf")):
                    assert links.nth(i).get_attribute("href") == f"/api/jobs/1/export?format={fmt}"
                    assert links.nth(i).get_attribute("download") == f"job-1-{fmt}.zip"
            with page.expect_download(timeout=60_000) as info:
                page.click(f"{row} a.export-link[data-format='sofa']")
            download = info.value
            assert download.suggested_filename == "job-1-sofa.zip"
            saved = tmp_path / download.suggested_filename
            download.save_as(saved)
            with zipfile.ZipFile(saved) as zf:
                assert sorted(zf.namelist()) == ["job-1-sofa/probe_path.csv", "job-1-sofa/scene.py", "job-1-sofa/twin.json"]
        finally:
            page.close()
    finally:
        server.stop()
