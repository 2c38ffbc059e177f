"""Shutdown noise: a Dask client collected after its event loop closed (Ctrl-C right
after a job started) must not print a traceback; any other unraisable error must."""

import sys
from types import SimpleNamespace

from app.server import db as dbm
from app.server.jobs.registry import Registry
from app.server.jobs.runner import WARM_IMPORTS, JobRunner, quiet_client_gc
from app.server.settings import Settings


class Client:  # stands in for distributed.Client: only the qualified name matters
    def __del__(self):
        pass


def _client_del():
    return Client.__del__


def test_the_closed_loop_noise_is_dropped_and_everything_else_is_kept(monkeypatch):
    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)
    quiet_client_gc()
    quiet_client_gc()  # idempotent: one wrapper, not two
    noise = SimpleNamespace(exc_type=RuntimeError, exc_value=RuntimeError("IOLoop is closed"), object=_client_del())
    other_object = SimpleNamespace(exc_type=RuntimeError, exc_value=RuntimeError("IOLoop is closed"), object=len)
    other_error = SimpleNamespace(exc_type=ValueError, exc_value=ValueError("IOLoop is closed"), object=_client_del())
    for u in (noise, other_object, other_error):
        sys.unraisablehook(u)
    assert seen == [other_object, other_error]


def test_the_local_workers_run_the_filter_and_import_core_first(tmp_path):
    """Both worker plugins ran: the shutdown-noise filter, and core imported before any
    job (two job threads importing core at once handed one a half-run module)."""
    engine = dbm.make_engine(f"sqlite:///{tmp_path / 'db.sqlite'}")
    runner = JobRunner(Settings(data_dir=str(tmp_path), workers=1), dbm.make_sessionmaker(engine), Registry())
    runner.start()
    try:
        flags = runner.client.run(lambda: bool(getattr(sys.unraisablehook, "_tissuetwin_quiet", False)))
        assert list(flags.values()) == [True]
        missing = runner.client.run(lambda: [m for m in WARM_IMPORTS if m not in sys.modules])
        assert list(missing.values()) == [[]]
    finally:
        runner.close()
        engine.dispose()
