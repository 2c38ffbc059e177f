"""Two dashboard tabs, each with its embedded viewer (issue 19, item 6), in a real headless
browser (Debian chromium + playwright): the "view" button of one tab shows the run in that
tab's viewer only, and the "ICP init" button of the other opens picking in its own viewer
only. Each dashboard tab names its viewer by a token in the iframe's websocket path.
"""

from __future__ import annotations

import time

import httpx
import pytest

from tests.app._server import Server
from tests.app.test_browser import _until
from tests.app.conftest import needs_chromium

pytestmark = [pytest.mark.slow, needs_chromium]


def _tabs(url) -> list[dict]:
    return httpx.get(f"{url}/api/viewer").json().get("tabs", [])


def _token(page) -> str:
    return page.evaluate("sessionStorage.getItem('tt-viewer-tab')")


def test_view_and_icp_buttons_act_on_their_own_tab(replayed, chromium):
    server = Server(replayed, viewer=True)
    context = chromium.new_context(viewport={"width": 1300, "height": 1300})
    try:
        a, b = context.new_page(), context.new_page()
        for page in (a, b):
            page.goto(server.url + "/")
            page.wait_for_selector("body[data-ready='1']")
            page.frame_locator("#viewer-frame").locator("canvas").first.wait_for(timeout=60_000)
        ta, tb = _token(a), _token(b)
        assert ta and tb and ta != tb
        tabs = _until(lambda: (t := _tabs(server.url)) and {x["token"] for x in t} == {ta, tb} and t,
                      "both viewer tabs connected with their dashboard's token")
        assert len(tabs) == 2

        a.bring_to_front()  # a background tab gets no animation frames: playwright's click waits for them
        a.click("#jobs-table tr[data-job-id='1'] .view-btn")
        by = _until(lambda: (t := {x["token"]: x for x in _tabs(server.url)}) and t[ta]["run_id"] == 1 and t,
                    "the run in tab A's viewer")
        a.frame_locator("#viewer-frame").get_by_text("frame 0 /", exact=False).wait_for(timeout=30_000)
        time.sleep(1.0)  # anything sent to tab B would have arrived by now
        by = {x["token"]: x for x in _tabs(server.url)}
        assert by[ta]["run_id"] == 1 and by[ta]["sequence"] == "seq01"
        assert by[tb]["run_id"] is None, "tab B's viewer followed tab A's view button"

        b.bring_to_front()
        b.click("#sessions-table tr[data-session-id] .icp-btn")
        _until(lambda: {x["token"]: x for x in _tabs(server.url)}[tb]["mode"] == "icp", "ICP mode in tab B's viewer")
        time.sleep(1.0)
        by = {x["token"]: x for x in _tabs(server.url)}
        assert by[ta]["mode"] == "replay" and by[ta]["run_id"] == 1, "tab A's viewer followed tab B's ICP button"

        # a reloaded dashboard tab keeps its token, and its new viewer opens what it last showed
        a.bring_to_front()
        a.reload()
        a.wait_for_selector("body[data-ready='1']")
        assert _token(a) == ta
        _until(lambda: (t := [x for x in _tabs(server.url) if x["token"] == ta]) and t[-1]["run_id"] == 1,
               "tab A's reloaded viewer showing its run again")
    finally:
        context.close()
        server.stop()
