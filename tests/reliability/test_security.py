"""Security of the workbench (issue 7, part 3), against the live loopback server.

* It binds loopback by default and warns when told to bind anything else.
* Session paths: only folders under ``--session-root`` (after resolving ``..`` and
  symlinks), no symlink inside a session leading out of it, no unusable path reaching the
  file system (NUL bytes, over-long names).
* Uploads: zip-slip (``..``, absolute, drive letters, backslashes), symlink members,
  encrypted members, bad CRCs, zip bombs, duplicate or clashing names and non-zips are
  refused and leave nothing behind; the size limit cuts the body off while it streams in.
* Job parameters are validated (pydantic, unknown fields refused, NaN and lone surrogates
  refused before they are stored).
* No route reads arbitrary files: the inventory of routes that take a path is fixed here,
  and the artifact download and the static files refuse every way out of their folder.
"""

from __future__ import annotations

import io
import json
import os
import select
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from tests.app._server import ROOT, _free_port, listening_addresses
from app.server.main import UPLOAD_OVERHEAD

FINAL = {"done", "failed", "cancelled", "interrupted"}


# ------------------------------------------------------------------------------ helpers
def raw_request(port: int, head: str, body: bytes = b"", read_timeout: float = 30.0) -> tuple[int, bytes]:
    """Send ``head`` (request line and headers, no final blank line) and ``body`` over a
    plain socket (no client-side URL normalisation); return (status, response body)."""
    with socket.create_connection(("127.0.0.1", port), timeout=read_timeout) as s:
        s.sendall(head.encode("latin-1") + b"\r\n\r\n" + body)
        return _read_response(s)


def _read_response(s: socket.socket) -> tuple[int, bytes]:
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1])
    length = next((int(line.split(b":", 1)[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:")), None)
    while length is not None and len(rest) < length:
        chunk = s.recv(65536)
        if not chunk:
            break
        rest += chunk
    return status, rest


def _zip(entries: list[tuple[zipfile.ZipInfo | str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for info, data in entries:
            zf.writestr(info, data)
    return buf.getvalue()


def _flag_encrypted(data: bytes, name: str) -> bytes:
    """``data`` (a zip) with member ``name`` flagged encrypted in the central directory
    (``zipfile`` clears the flag when it writes)."""
    out = bytearray(data)
    i = out.find(b"PK\x01\x02")
    while i >= 0:
        n = int.from_bytes(out[i + 28:i + 30], "little")
        if out[i + 46:i + 46 + n] == name.encode():
            out[i + 8] |= 0x1
            return bytes(out)
        i = out.find(b"PK\x01\x02", i + 4)
    raise KeyError(name)


def _session_entries(root: Path, prefix: str = "s/") -> list[tuple[str, bytes]]:
    return [(prefix + p.relative_to(root).as_posix(), p.read_bytes()) for p in sorted(root.rglob("*")) if p.is_file()]


def _stored(live) -> tuple[list, list]:
    """What the server holds: its sessions and the folders under <data>/sessions."""
    sessions = httpx.get(f"{live.url}/api/sessions").json()
    return sessions, sorted(p.name for p in (live.data / "sessions").iterdir()) if (live.data / "sessions").is_dir() else []


# ------------------------------------------------------------------------------ binding
def test_serve_binds_loopback_by_default_and_warns_elsewhere(live, tmp_path):
    from app.cli import build_parser
    from app.cli_serve import bind_warning, is_loopback

    parser = build_parser()
    assert parser.parse_args(["serve"]).host == "127.0.0.1" and parser.parse_args(["demo"]).host == "127.0.0.1"
    assert listening_addresses(live.server.port) == {"0100007F"}  # the live server: 127.0.0.1 only

    for host in ("127.0.0.1", "localhost", "::1", "[::1]", "127.0.0.2"):
        assert is_loopback(host) and bind_warning(host) is None, host
    for host in ("0.0.0.0", "::", "192.168.1.20", "lab-pc.example.org"):
        warning = bind_warning(host)
        assert not is_loopback(host) and warning.startswith(f"warning: serving on {host}, reachable from other machines")
        assert "no authentication" in warning and "--session-root" in warning
    assert "--session-root" not in bind_warning("0.0.0.0", [Path("/lab")])

    # the command itself prints it first thing (killed before it would start listening)
    cmd = [sys.executable, "-m", "app.cli", "serve", "--host", "0.0.0.0", "--port", str(_free_port()),
           "--no-viewer", "--data", str(tmp_path / "data")]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        line = proc.stderr.readline()
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
    assert line.startswith("warning: serving on 0.0.0.0, reachable from other machines: the workbench has no authentication")


# ------------------------------------------------------------------------------ session paths
def test_session_paths_outside_the_roots_or_escaping_are_refused(live, tmp_path):
    before = _stored(live)
    outside = Path(tempfile.mkdtemp(prefix="tt-outside-"))  # /tmp, not under the roots
    try:
        shutil.copytree(live.session, outside / "s")
        inside = Path(shutil.copytree(live.session, tmp_path / "s")).resolve()
        (tmp_path / "link").symlink_to(outside / "s", target_is_directory=True)
        cases = [
            (str(outside / "s"), 403, "outside the folders sessions may be registered from"),
            (f"{inside}/../../../../../../../{outside.relative_to('/')}/s", 403, "outside the folders"),  # ../ traversal
            (str(tmp_path / "link"), 403, "outside the folders"),  # a symlinked folder: judged where it leads
            ("/etc", 403, "outside the folders"),
            ("/etc/passwd", 422, "not a directory"),
            ("nope\u0000/x", 422, "not a usable path"),
            (str(tmp_path / ("x" * 300)), 422, "not a usable path"),  # a name longer than the file system allows
            ("x" * 4097, 422, "at most 4096 characters"),
        ]
        for path, status, message in cases:
            r = httpx.post(f"{live.url}/api/sessions", json={"path": path})
            assert r.status_code == status, (path, r.text)
            assert message in json.dumps(r.json()), (path, r.text)
            assert "root:" not in r.text  # nothing of a file's content comes back

        # a cloud inside the session that is a symlink to a file outside it: refused, named
        cloud = inside / "sequences" / "seq00" / "clouds" / "000003.ply"
        cloud.unlink()
        cloud.symlink_to(outside / "s" / "sequences" / "seq00" / "clouds" / "000003.ply")
        r = httpx.post(f"{live.url}/api/sessions", json={"path": str(inside)})
        assert r.status_code == 422
        assert r.json()["detail"] == f"{cloud}: is a symlink leading out of the session folder; copy the data in instead"
        # one that stays inside is fine
        cloud.unlink()
        cloud.symlink_to("000002.ply")
        r = httpx.post(f"{live.url}/api/sessions", json={"path": str(inside)})
        assert r.status_code == 201, r.text
        assert httpx.delete(f"{live.url}/api/sessions/{r.json()['id']}").status_code == 204
        assert (inside / "session.json").exists()  # a registered folder is never deleted
    finally:
        shutil.rmtree(outside)
    assert _stored(live) == before


# ------------------------------------------------------------------------------ uploads
def test_uploads_refuse_zip_slip_bombs_and_malformed_archives(live, tmp_path):
    before = _stored(live)
    good = _session_entries(live.session)

    def member(name: str, mode: int) -> zipfile.ZipInfo:
        info = zipfile.ZipInfo(name)
        info.external_attr = mode << 16
        return info

    corrupt = bytearray(_zip(good))  # flip bytes inside the first member's compressed data
    corrupt[60:64] = bytes(b ^ 0xFF for b in corrupt[60:64])
    cases = [
        ([("../../escaped.txt", b"x")] + good, 422, "unsafe path in zip: '../../escaped.txt'"),
        ([("s/../../escaped.txt", b"x")] + good, 422, "unsafe path in zip"),
        ([("/tmp/escaped.txt", b"x")] + good, 422, "unsafe path in zip: '/tmp/escaped.txt'"),
        ([("C:/escaped.txt", b"x")] + good, 422, "unsafe path in zip"),
        ([("..\\escaped.txt", b"x")] + good, 422, "unsafe path in zip"),
        ([(member("s/link", stat.S_IFLNK | 0o777), b"/etc/passwd")] + good, 422, "symlink in zip: 's/link'"),
        (_flag_encrypted(_zip([("s/secret.txt", b"x")] + good), "s/secret.txt"), 422, "encrypted member in zip: 's/secret.txt'"),
        (good + [("s/session.json", b"{}")], 422, "the zip holds 's/session.json' twice"),
        (good + [("s/calibration/corners.csv/x", b"x")], 422, "both as a file and a folder"),
        ([("s/zeros.bin", bytes(3 * live.max_upload_bytes))] + good, 413, "zip expands to more than"),  # a zip bomb
        (bytes(corrupt), 422, "cannot unpack"),
        (b"PK\x03\x04 not really a zip", 422, "not a zip file"),
    ]
    for entries, status, message in cases:
        body = entries if isinstance(entries, bytes) else _zip(entries)
        assert len(body) < live.max_upload_bytes  # refused for what it is, not for its size
        r = httpx.post(f"{live.url}/api/sessions/upload", files={"file": ("evil.zip", body, "application/zip")}, timeout=60)
        assert r.status_code == status, (message, r.text)
        assert message in r.json()["detail"], (message, r.text)
    assert not list(live.data.parent.rglob("escaped.txt")) and not Path("/tmp/escaped.txt").exists()
    assert _stored(live) == before  # nothing stored, nothing left behind

    ok = httpx.post(f"{live.url}/api/sessions/upload", files={"file": ("ok.zip", _zip(good), "application/zip")}, timeout=60)
    assert ok.status_code == 201, ok.text  # the same session, zipped plainly, is accepted
    assert httpx.delete(f"{live.url}/api/sessions/{ok.json()['id']}").status_code == 204
    assert _stored(live) == before


def test_zip_member_count_is_limited(tmp_path):
    from app.server.errors import Invalid
    from app.server.services.sessions import safe_extract

    archive = tmp_path / "many.zip"
    archive.write_bytes(_zip([(f"f{i}", b"") for i in range(6)]))
    with pytest.raises(Invalid, match="the zip holds 6 entries, more than 5"):
        safe_extract(archive, tmp_path / "out", max_bytes=10**6, max_members=5)
    assert not (tmp_path / "out").exists()


def test_body_size_limits_are_enforced_while_the_body_streams_in(live):
    before = _stored(live)
    total = 25 * live.max_upload_bytes  # 50 MB against a 2 MB limit
    boundary = "b0undary"
    head = (f"POST /api/sessions/upload HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            f"Content-Type: multipart/form-data; boundary={boundary}")
    part = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"big.zip\"\r\n"
            "Content-Type: application/zip\r\n\r\n").encode()

    # announced too large: refused before a byte of the body is sent (Starlette answers
    # this one before any handler; the app rewrites it into the documented JSON body)
    status, body = raw_request(live.server.port, f"{head}\r\nContent-Length: {total}", b"")
    assert status == 413
    assert json.loads(body) == {"detail": f"request body larger than {live.max_upload_bytes + UPLOAD_OVERHEAD} bytes"}

    # no length announced (chunked): cut off once the limit is passed, long before the end
    sent = 0
    with socket.create_connection(("127.0.0.1", live.server.port), timeout=60) as s:
        s.sendall(f"{head}\r\nTransfer-Encoding: chunked\r\n\r\n".encode())
        chunk = part + bytes(256 * 1024 - len(part))
        while sent < total:
            if select.select([s], [], [], 0)[0]:
                break  # the server answered: stop sending
            try:
                s.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
            except (BrokenPipeError, ConnectionResetError):
                break
            sent += len(chunk)
            chunk = bytes(256 * 1024)
        status, body = _read_response(s)
    assert status == 413 and b"larger than" in body
    print(f"\nchunked upload against a {live.max_upload_bytes} B limit: 413 after {sent} of {total} B sent")
    assert sent < total / 2, f"sent {sent} of {total} bytes before the 413"

    # JSON routes have their own small limit
    r = httpx.post(f"{live.url}/api/sessions", content=json.dumps({"path": "x" * 2_000_000}),
                   headers={"content-type": "application/json"})
    assert r.status_code == 413 and "larger than" in r.json()["detail"]
    assert _stored(live) == before


# ------------------------------------------------------------------------------ job parameters
def test_job_parameters_are_validated_before_anything_is_stored(live):
    types = {t["name"]: t for t in httpx.get(f"{live.url}/api/job-types").json()}
    n_before = len(httpx.get(f"{live.url}/api/jobs", params={"limit": 1000}).json())
    sid = live.session_id
    bad = [{"type": name, "params": {"session_id": sid, "no_such_parameter": 1}} for name in types]  # every type: extra="forbid"
    bad += [
        {"type": "replay", "params": {"session_id": sid, "youngs_modulus": -1}},
        {"type": "replay", "params": {"session_id": sid, "grid": [13, 5, 5, 5]}},
        {"type": "replay", "params": {"session_id": sid, "grid": [1000, 5, 5]}},
        {"type": "replay", "params": {"session_id": "1; drop table jobs"}},
        {"type": "sweep", "params": {"session_id": sid, "youngs": [1.0] * 61, "per_decade": 99}},
        {"type": "generate", "params": {"name": "../../escape"}},
        {"type": "generate", "params": {"name": "/abs"}},
        {"type": "replay", "params": {"session_id": sid, "sequences": ["\ud800"]}},  # a lone surrogate
        {"type": "replay", "params": {"session_id": sid, "effects": [{"kind": "gravity", "g": [0, 0, 1e400]}]}},
    ]
    for body in bad:
        r = httpx.post(f"{live.url}/api/jobs", content=json.dumps(body), headers={"content-type": "application/json"})
        assert r.status_code == 422, (body, r.text)
    for raw in (b'{"type": "replay", "params": {"session_id": %d, "youngs_modulus": NaN}}' % sid,
                b'{"type": "replay", "params": {"session_id": %d, "youngs_modulus": Infinity}}' % sid):
        r = httpx.post(f"{live.url}/api/jobs", content=raw, headers={"content-type": "application/json"})
        assert r.status_code == 422 and "must be finite" in r.text, r.text
    for missing in (0, -1, 2**63, 10**30):  # ids no row can have: 404, not a database error
        r = httpx.post(f"{live.url}/api/jobs", json={"type": "replay", "params": {"session_id": missing}})
        assert r.status_code in (404, 422), (missing, r.text)
        assert httpx.get(f"{live.url}/api/jobs/{missing}").status_code in (404, 422)
    jobs = httpx.get(f"{live.url}/api/jobs", params={"limit": 1000})
    assert jobs.status_code == 200 and len(jobs.json()) == n_before  # nothing queued, the listing renders


# ------------------------------------------------------------------------------ files
def test_only_two_routes_take_a_path_and_neither_reads_outside_its_folder(live, tmp_path):
    spec = httpx.get(f"{live.url}/openapi.json").json()
    takes_path = set()
    for route, ops in spec["paths"].items():
        for method, op in ops.items():
            names = {p["name"] for p in op.get("parameters", [])}
            body = op.get("requestBody", {}).get("content", {})
            for media in body.values():
                ref = media.get("schema", {}).get("$ref", "")
                schema = spec["components"]["schemas"].get(ref.rsplit("/", 1)[-1], {}) if ref else media.get("schema", {})
                names |= set(schema.get("properties", {}))
            for n in names:
                if any(w in n.lower() for w in ("path", "file", "dir", "folder")):
                    takes_path.add((method.upper(), route, n))
    # reviewed: a registered folder (checked against the session roots) and an artifact
    # (inside its job's folder), and the uploaded zip itself; a new one must be reviewed too
    assert takes_path == {("POST", "/api/sessions", "path"), ("GET", "/api/jobs/{job_id}/artifacts/{path}", "path"),
                          ("POST", "/api/sessions/upload", "file")}

    job = httpx.post(f"{live.url}/api/jobs", json={"type": "replay", "params": {
        "session_id": live.session_id, "grid": [4, 3, 3]}}).json()
    deadline = time.monotonic() + 120
    while (job := httpx.get(f"{live.url}/api/jobs/{job['id']}").json())["status"] not in FINAL:
        assert time.monotonic() < deadline, job
        time.sleep(0.2)
    assert job["status"] == "done", job["error"]
    folder = live.data / "jobs" / str(job["id"])
    secret = tmp_path / "secret.txt"
    secret.write_text("root:x:0:0 TOP-SECRET-CONTENT")
    (folder / "leak.txt").symlink_to(secret)
    (folder / "leakdir").symlink_to(tmp_path, target_is_directory=True)

    port, base = live.server.port, f"/api/jobs/{job['id']}/artifacts"
    assert raw_request(port, f"GET {base}/replay.json HTTP/1.1\r\nHost: x\r\nConnection: close")[0] == 200
    for target in ("../../workbench.db", "..%2F..%2Fworkbench.db", "%2e%2e/%2e%2e/workbench.db", "%2E%2E%2F%2E%2E%2Fworkbench.db",
                   "/etc/passwd", "//etc/passwd", "%2Fetc%2Fpasswd", "sub/../../../workbench.db", "..", ".", "",
                   "leak.txt", "leakdir/secret.txt", "%00", "replay.json%00.png", "..\\..\\workbench.db",
                   "x" * 5000):
        status, body = raw_request(port, f"GET {base}/{target} HTTP/1.1\r\nHost: x\r\nConnection: close")
        assert status in (400, 404, 422), (target, status)
        assert b"SQLite" not in body and b"root:" not in body and b"TOP-SECRET" not in body, target
    listed = {a["path"] for a in httpx.get(f"{live.url}{base}").json()}
    assert "replay.json" in listed and not {p for p in listed if p.startswith(("leak", "leakdir"))}

    for target in ("../app/server/settings.py", "..%2Fpyproject.toml", "%2e%2e/%2e%2e/etc/passwd", "/etc/passwd"):
        status, body = raw_request(port, f"GET /static/{target} HTTP/1.1\r\nHost: x\r\nConnection: close")
        assert status == 404 and b"BaseSettings" not in body and b"root:" not in body, target
