"""The job service on a real PostgreSQL server (``DATABASE_URL``), and on an existing Dask
cluster started by hand: the compose set-up (docker-compose.yml) without Docker.

A throwaway PostgreSQL server runs on loopback for the module: ``initdb`` into a temporary
folder and ``pg_ctl start`` on a free port (as the ``postgres`` user when the tests run as
root: PostgreSQL refuses to run as root). Its time zone is deliberately not UTC. The
binaries are Debian's ``postgresql`` package, which ``scripts/setup.sh`` installs.
"""

from __future__ import annotations

import datetime as dt
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from sqlalchemy import inspect, select, text

from app.server import db as dbm
from app.server.jobs.runner import WARM_IMPORTS
from app.server.errors import Invalid
from tests.app.test_server import Server, _free_port, _wait

FINAL = {"done", "failed", "cancelled", "interrupted"}
PG_TIMEZONE = "Asia/Kolkata"  # UTC+05:30 all year: a non-UTC session time zone is easy to see


def postgres_bindir() -> Path:
    """The folder holding ``initdb`` and ``pg_ctl``: ``pg_config --bindir``, else the newest
    ``/usr/lib/postgresql/<version>/bin`` (Debian), else ``PATH``.

    Raises:
        FileNotFoundError: no PostgreSQL server binaries (``scripts/setup.sh`` installs them).
    """
    candidates = []
    if shutil.which("pg_config"):
        out = subprocess.run(["pg_config", "--bindir"], capture_output=True, text=True, check=False)
        if out.returncode == 0 and out.stdout.strip():
            candidates.append(Path(out.stdout.strip()))
    versions = [p for p in Path("/usr/lib/postgresql").glob("*/bin") if p.parent.name.isdigit()]
    candidates += sorted(versions, key=lambda p: int(p.parent.name), reverse=True)
    if shutil.which("initdb"):
        candidates.append(Path(shutil.which("initdb")).resolve().parent)
    for folder in candidates:
        if (folder / "initdb").is_file() and (folder / "pg_ctl").is_file():
            return folder
    raise FileNotFoundError("PostgreSQL server binaries (initdb, pg_ctl) not found; run scripts/setup.sh "
                            "(it installs Debian's postgresql package)")


class PostgresServer:
    """A throwaway PostgreSQL server on 127.0.0.1: trust authentication for the superuser
    ``tissuetwin``, fsync off, in a temporary folder removed by :meth:`stop`.

    Raises:
        RuntimeError: initdb or pg_ctl failed (with their output), or running as root
            without a ``postgres`` user to run the server as.
    """

    user = "tissuetwin"

    def __init__(self, timezone: str = PG_TIMEZONE):
        import psycopg

        self.bindir = postgres_bindir()
        self.root = Path(tempfile.mkdtemp(prefix="tissuetwin-pg-"))
        self.data, self.logfile = self.root / "db", self.root / "server.log"
        self.as_user: list[str] = []
        if os.geteuid() == 0:  # "root" execution of the PostgreSQL server is not permitted
            try:
                shutil.chown(self.root, user="postgres")
            except LookupError as exc:
                raise RuntimeError("running as root, but there is no 'postgres' user to run PostgreSQL as "
                                   "(Debian's postgresql package creates it)") from exc
            self.as_user = ["runuser", "-u", "postgres", "--"]
        self.port = _free_port()
        self._run([self.bindir / "initdb", "-D", self.data, "-U", self.user, "--auth=trust", "-E", "UTF8",
                   "--locale=C.UTF-8", "--no-sync"])
        options = (f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off "
                   f"-c full_page_writes=off -c timezone={timezone}")
        self._run([self.bindir / "pg_ctl", "-D", self.data, "-l", self.logfile, "-w", "-t", "60", "-o", options, "start"])
        self.conninfo = f"host=127.0.0.1 port={self.port} user={self.user} dbname=postgres"
        with psycopg.connect(self.conninfo, autocommit=True) as conn:
            assert conn.execute("show timezone").fetchone()[0] == timezone

    def _run(self, args: list) -> None:
        out = subprocess.run(self.as_user + [str(a) for a in args], capture_output=True, text=True, check=False)
        if out.returncode != 0:
            log = self.logfile.read_text()[-2000:] if self.logfile.exists() else ""
            raise RuntimeError(f"{Path(args[0]).name} failed ({out.returncode}): {out.stdout}{out.stderr}{log}")

    def create_database(self, name: str) -> str:
        """Create database ``name``; returns its ``postgresql+psycopg://`` SQLAlchemy URL."""
        import psycopg

        with psycopg.connect(self.conninfo, autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return f"postgresql+psycopg://{self.user}@127.0.0.1:{self.port}/{name}"

    def query(self, database: str, sql: str, params=()) -> list[tuple]:
        """Rows of ``sql`` on ``database``, read with psycopg directly (not through the app)."""
        import psycopg

        with psycopg.connect(f"host=127.0.0.1 port={self.port} user={self.user} dbname={database}") as conn:
            return conn.execute(sql, params).fetchall()

    def stop(self) -> None:
        if self.data.exists():
            subprocess.run(self.as_user + [str(self.bindir / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "stop"],
                           capture_output=True, check=False)
        shutil.rmtree(self.root, ignore_errors=True)


@pytest.fixture(scope="module")
def postgres():
    server = PostgresServer()
    yield server
    server.stop()


_counter = iter(range(1, 10_000))


@pytest.fixture
def pg_database(postgres) -> tuple[str, str]:
    """A fresh database on the module's server: (name, SQLAlchemy URL)."""
    name = f"tt{next(_counter)}"
    return name, postgres.create_database(name)


@pytest.fixture(params=["sqlite", "postgresql"])
def any_url(request, tmp_path) -> str:
    """The same checks on both back-ends: a SQLite file and a fresh PostgreSQL database
    (given as plain ``postgresql://``, which the app maps to the psycopg 3 driver)."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'workbench.db'}"
    _, url = request.getfixturevalue("pg_database")
    return url.replace("postgresql+psycopg://", "postgresql://")


# ------------------------------------------------------------------ the persistence layer
def test_both_backends_store_the_same(any_url):
    engine = dbm.make_engine(any_url)
    try:
        factory = dbm.make_sessionmaker(engine)
        before = dbm.utcnow()
        with factory.begin() as db:
            s = dbm.SessionRecord(name="s", path="/data/s", source="registered")
            db.add(s)
            db.flush()
            result = {"best": math.nan, "table": [{"E": 10.0, "error": math.inf}, {"E": 100.0, "error": 1.5e-3}],
                      "nested": {"values": [1, -math.inf, 0.25]}, "ok": True, "name": "é"}
            job = dbm.JobRecord(type="sweep", params={"youngs": [10.0, 100.0]}, session_id=s.id, status=dbm.DONE,
                                result=result, started_at=before, finished_at=dbm.utcnow())
            db.add(job)
        with factory() as db:
            got = db.get(dbm.JobRecord, job.id)
            # NaN and +-inf become null (PostgreSQL's json refuses NaN; the API shows null either way)
            assert got.result == {"best": None, "table": [{"E": 10.0, "error": None}, {"E": 100.0, "error": 1.5e-3}],
                                  "nested": {"values": [1, None, 0.25]}, "ok": True, "name": "é"}
            assert got.params == {"youngs": [10.0, 100.0]}
            for stamp in (got.created_at, got.started_at, got.finished_at):
                assert stamp.utcoffset() == dt.timedelta(0), stamp  # UTC, whatever the server's time zone
            assert got.started_at == before  # microseconds survive the round trip
            assert before <= got.finished_at <= got.created_at <= dbm.utcnow()  # created_at is set at the flush
            assert db.get(dbm.SessionRecord, s.id).created_at.tzinfo is not None
        with pytest.raises(Invalid, match="session name is 201 characters long; at most 200"):
            dbm.SessionRecord(name="n" * 201, path="/data/x", source="uploaded")
        with factory() as db, pytest.raises(Exception, match="naive datetime"):
            db.add(dbm.JobRecord(type="replay", params={}, started_at=dt.datetime(2026, 1, 1)))
            db.flush()
        with factory.begin() as db:
            db.add(dbm.JobRecord(type="replay", params={}, status=dbm.RUNNING))
        assert dbm.mark_interrupted(factory) == 1
        with factory() as db:
            statuses = dict(db.execute(select(dbm.JobRecord.id, dbm.JobRecord.status)).all())
        assert statuses == {job.id: dbm.DONE, job.id + 1: dbm.INTERRUPTED}
    finally:
        engine.dispose()


def test_a_database_of_an_earlier_version_gets_the_new_columns(any_url):
    """``create_all`` does not add columns to existing tables: a database made before
    ``jobs.dask_token`` existed gets it at start-up, and its rows survive."""
    engine = dbm.make_engine(any_url)
    try:
        factory = dbm.make_sessionmaker(engine)
        with factory.begin() as db:
            db.add(dbm.JobRecord(type="replay", params={"grid": [4, 3, 3]}, status=dbm.RUNNING))
        with engine.begin() as conn:
            conn.execute(text("ALTER TABLE jobs DROP COLUMN dask_token"))  # the earlier schema
        assert "dask_token" not in {c["name"] for c in inspect(engine).get_columns("jobs")}
        factory = dbm.make_sessionmaker(engine)
        assert "dask_token" in {c["name"] for c in inspect(engine).get_columns("jobs")}
        with factory.begin() as db:
            job = db.execute(select(dbm.JobRecord)).scalar_one()
            assert job.params == {"grid": [4, 3, 3]} and job.dask_token is None
            job.dask_token = "tt-1-abc"
        assert dbm.active_tokens(factory) == ["tt-1-abc"]
        dbm.mark_interrupted(factory)
        assert dbm.active_tokens(factory) == []
    finally:
        engine.dispose()


def test_servers_starting_at_once_create_the_tables_once(pg_database, postgres):
    """Several workbench processes starting together against one empty database (one
    engine each, as separate processes have) all come up with one set of tables."""
    name, url = pg_database
    engines = [dbm.make_engine(url) for _ in range(6)]
    barrier, errors = threading.Barrier(len(engines)), []

    def start(engine):
        barrier.wait()
        try:
            dbm.make_sessionmaker(engine)
        except Exception as exc:  # noqa: BLE001 - collected and asserted below
            errors.append(exc)

    threads = [threading.Thread(target=start, args=(e,)) for e in engines]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for e in engines:
        e.dispose()
    assert not errors, errors
    tables = postgres.query(name, "select tablename from pg_tables where schemaname = 'public' order by 1")
    assert tables == [("jobs",), ("sessions",)]


def test_postgres_url_forms():
    assert dbm.normalize_url("postgres://u:p%40w@db:5432/tt") == "postgresql+psycopg://u:p%40w@db:5432/tt"
    assert dbm.normalize_url("postgresql://u@db/tt") == "postgresql+psycopg://u@db/tt"
    assert dbm.normalize_url("postgresql+psycopg://u@db/tt") == "postgresql+psycopg://u@db/tt"
    assert dbm.normalize_url("sqlite:////data/workbench.db") == "sqlite:////data/workbench.db"


# ------------------------------------------------------------------ the compose set-up, by hand
class DaskCluster:
    """``dask scheduler`` and two ``dask worker`` processes (one thread each) on loopback,
    started with the commands and environment docker-compose.yml gives them."""

    def __init__(self, logdir: Path):
        bindir = Path(sys.executable).parent
        self.port = _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False",
               "DASK_DISTRIBUTED__SCHEDULER__ACTIVE_MEMORY_MANAGER__START": "False", "OMP_NUM_THREADS": "1",
               "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
        self.log = open(logdir / "dask.log", "w")
        self.procs = [subprocess.Popen([bindir / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                                        "--no-dashboard"], env=env, stdout=self.log, stderr=subprocess.STDOUT,
                                       start_new_session=True)]
        for i in (1, 2):
            self.procs.append(subprocess.Popen(
                [bindir / "dask", "worker", self.address, "--nthreads", "1", "--name", f"worker-{i}", "--host", "127.0.0.1",
                 "--no-dashboard"], env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True))
        from distributed import Client

        with Client(self.address, timeout=60) as client:
            client.wait_for_workers(2, timeout=60)

    def stop(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        self.log.close()


def _submit_all(url: str, bodies: list[dict]) -> list[httpx.Response]:
    """POST every body to /api/jobs at once (one thread each)."""
    with ThreadPoolExecutor(len(bodies)) as pool:
        return list(pool.map(lambda b: httpx.post(f"{url}/api/jobs", json=b, timeout=60), bodies))


@pytest.mark.slow
def test_compose_setup_without_docker(small_session, postgres, pg_database, tmp_path, monkeypatch):
    """docker-compose.yml's set-up on loopback: ``tissuetwin serve`` with DATABASE_URL on
    PostgreSQL and TISSUETWIN_SCHEDULER on a hand-started Dask scheduler with two workers,
    all sharing one data folder. A real job runs to done on the workers; twelve jobs
    submitted at once are all stored; the server is killed and restarted (a new process,
    a new engine): the finished job is intact, the others say they were interrupted."""
    from distributed import Client

    name, url = pg_database
    cluster = DaskCluster(tmp_path)
    try:
        monkeypatch.setenv("DATABASE_URL", url)
        monkeypatch.setenv("TISSUETWIN_SCHEDULER", cluster.address)
        data = tmp_path / "shared-data"  # the volume the workbench and the workers share
        server = Server(data)
        try:
            assert httpx.get(f"{server.url}/api/config").json()["scheduler"] == cluster.address
            sid = httpx.post(f"{server.url}/api/sessions", json={"path": str(small_session)}).json()["id"]
            r = httpx.post(f"{server.url}/api/jobs", json={"type": "replay", "params": {"session_id": sid, "sequences": ["seq02"]}})
            assert r.status_code == 201, r.text
            done = _wait(server.url, r.json()["id"], FINAL)
            assert done["status"] == "done", done["error"]
            assert done["result"]["sequences"]["seq02"]["status"] == "ok"
            assert (data / "jobs" / str(done["id"]) / "replay.json").is_file()  # written by a worker
            # twelve sweeps submitted at once: every request gets its own job
            sweep = {"type": "sweep", "params": {"session_id": sid, "e_min": 10, "e_max": 1e6, "per_decade": 4}}
            responses = _submit_all(server.url, [sweep] * 12)
            assert [x.status_code for x in responses] == [201] * 12, [x.text for x in responses if x.status_code != 201]
            long_ids = sorted(x.json()["id"] for x in responses)
            assert len(set(long_ids)) == 12
            _wait(server.url, long_ids[0], {"running"})
        finally:
            server.stop(signal.SIGKILL)  # a crash: no chance to mark anything

        rows = dict(postgres.query(name, "select id, status from jobs"))
        assert rows[done["id"]] == "done"
        assert {rows[i] for i in long_ids} <= {"queued", "running"} and "running" in {rows[i] for i in long_ids}

        server = Server(data)
        try:
            again = httpx.get(f"{server.url}/api/jobs/{done['id']}").json()
            assert again["status"] == "done" and again["result"] == done["result"]
            assert again["finished_at"] == done["finished_at"]
            assert dt.datetime.fromisoformat(again["finished_at"]).utcoffset() == dt.timedelta(0)
            files = {a["path"] for a in httpx.get(f"{server.url}/api/jobs/{done['id']}/artifacts").json()}
            assert {"replay.json", "seq02.npz"} <= files
            replay_json = httpx.get(f"{server.url}/api/jobs/{done['id']}/artifacts/replay.json")
            assert replay_json.status_code == 200 and '"seq02"' in replay_json.text
            lost = httpx.get(f"{server.url}/api/jobs", params={"status": "interrupted"}).json()
            assert sorted(j["id"] for j in lost) == long_ids
            assert all("server stopped" in j["error"] for j in lost)
            assert [s["id"] for s in httpx.get(f"{server.url}/api/sessions").json()] == [sid]
        finally:
            server.stop()
        assert postgres.query(name, "select status from jobs where id = %s", (done["id"],)) == [("done",)]
        with Client(cluster.address, timeout=30) as client:
            # the jobs ran on this cluster's two workers (tt-<job id>-<uuid>-job tasks)
            prefixes = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
            workers = sorted(w["name"] for w in client.scheduler_info()["workers"].values())
            # the server's plugin imported core on each worker before its jobs (see WARM_IMPORTS)
            missing = client.run(lambda: [m for m in WARM_IMPORTS if m not in sys.modules])
        assert workers == ["worker-1", "worker-2"]
        assert list(missing.values()) == [[], []], missing
        assert "tt" in prefixes, prefixes
    finally:
        cluster.stop()
