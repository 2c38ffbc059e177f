"""Dockerfile, .dockerignore and docker-compose.yml agree with the code they start.

No Docker engine runs in CI, so the container files are checked against the real thing
they name: every ``tissuetwin`` command parses with ``app.cli.build_parser()``, every
``dask`` command with distributed's own command-line parser, the environment is read
back through the workbench's ``Settings``, and the database URL, ports, volume and
torch pin match their counterparts (the postgres service, the viewer's port, the
``--data`` folder, pyproject.toml).
"""

from __future__ import annotations

import fnmatch
import json
import re
import shlex
import tomllib
from pathlib import Path

import pytest
import yaml

from app.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]
PYTHON_SERVICES = ["scheduler", "worker-1", "worker-2", "workbench"]


def dockerfile() -> list[tuple[str, str]]:
    """The Dockerfile's instructions as (KEYWORD, arguments), continuation lines joined
    and comment lines dropped, as Docker reads them."""
    out, current = [], ""
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        if line.strip().startswith("#") or not line.strip():
            continue
        current += line.rstrip()
        if current.endswith("\\"):
            current = current[:-1] + " "
            continue
        keyword, _, args = current.strip().partition(" ")
        out.append((keyword.upper(), args.strip()))
        current = ""
    return out


def instructions(keyword: str) -> list[str]:
    return [args for k, args in dockerfile() if k == keyword]


def exec_form(args: str) -> list[str]:
    """A CMD or HEALTHCHECK's JSON exec form."""
    return json.loads(args[args.index("["):])


def tissuetwin_commands() -> list[list[str]]:
    """Every ``tissuetwin ...`` command line in the Dockerfile (RUN, CMD) and docker-compose.yml."""
    commands = []
    for run in instructions("RUN"):
        for part in re.split(r"&&|;", run):
            words = shlex.split(part)
            if words and words[0] == "tissuetwin":
                commands.append(words)
    commands += [exec_form(c) for c in instructions("CMD")]
    commands += [s["command"] for s in SERVICES.values() if s.get("command", [""])[0] == "tissuetwin"]
    return commands


def parse(argv: list[str]):
    """argparse's namespace for a ``tissuetwin`` command (fails the test on an unknown flag)."""
    assert argv[0] == "tissuetwin"
    try:
        return build_parser().parse_args(argv[1:])
    except SystemExit:
        pytest.fail(f"`{shlex.join(argv)}` does not parse with app.cli.build_parser()")


def test_every_tissuetwin_command_parses():
    commands = tissuetwin_commands()
    assert len(commands) >= 3  # the build-time demo, the image's CMD, the compose workbench
    for argv in commands:
        parse(argv)
    served = [parse(c) for c in [exec_form(instructions("CMD")[0]), SERVICES["workbench"]["command"]]]
    for args in served:  # the container's loopback is unreachable from outside it
        assert args.command == "demo" and args.host == "0.0.0.0" and not args.no_serve


def test_one_data_folder_everywhere():
    """The image's demo session, the workbench's --data and the volume the workers mount
    are one folder (job artifacts and sessions are shared by path)."""
    folders = {parse(c).data for c in tissuetwin_commands()}
    assert len(folders) == 1
    data = folders.pop()
    assert f"TISSUETWIN_DATA={data}" in instructions("ENV")
    for name in PYTHON_SERVICES:
        assert f"data:{data}" in SERVICES[name]["volumes"], name
    assert "data" in COMPOSE["volumes"]


def test_python_services_run_the_same_image():
    images = {SERVICES[name]["image"] for name in PYTHON_SERVICES}
    assert len(images) == 1
    for name in PYTHON_SERVICES:
        assert SERVICES[name]["build"] == "."


def test_dask_commands_parse_and_agree_with_the_scheduler_address():
    import dask
    from click import UsageError
    from distributed.cli import dask_scheduler, dask_worker

    def ctx(command, sub: str, argv: list[str]):
        assert argv[:2] == ["dask", sub]
        try:
            return command.make_context(f"dask {sub}", argv[2:])
        except UsageError as exc:
            pytest.fail(f"`{shlex.join(argv)}`: {exc}")

    scheduler = ctx(dask_scheduler.main, "scheduler", SERVICES["scheduler"]["command"]).params
    address = f"tcp://scheduler:{scheduler['port']}"
    assert SERVICES["workbench"]["environment"]["TISSUETWIN_SCHEDULER"] == address
    workers = [name for name in SERVICES if name.startswith("worker")]
    assert len(workers) == 2
    names = set()
    for name in workers:
        params = ctx(dask_worker.main, "worker", SERVICES[name]["command"]).params
        assert params["scheduler"] == address and params["nthreads"] == 1
        names.add(params["name"])
        # the same setting the local cluster gets (app/server/jobs/runner.py): jobs may start processes
        env = SERVICES[name]["environment"]
        config = dask.config.collect_env({k: v for k, v in env.items() if k.startswith("DASK_")})
        assert config["distributed"]["worker"]["daemon"] is False
        assert SERVICES[name]["depends_on"]["scheduler"]["condition"] == "service_healthy"
    assert len(names) == 2
    health = " ".join(SERVICES["scheduler"]["healthcheck"]["test"])
    assert f"'127.0.0.1', {scheduler['port']}" in health


def test_database_url_points_at_the_postgres_service(monkeypatch):
    from sqlalchemy.engine import make_url

    from app.server.db import normalize_url
    from app.server.settings import Settings

    env = SERVICES["workbench"]["environment"]
    url = make_url(normalize_url(env["DATABASE_URL"]))
    pg = SERVICES["postgres"]["environment"]
    assert url.drivername == "postgresql+psycopg"
    assert (url.host, url.port) == ("postgres", 5432)
    assert (url.username, url.password, url.database) == (pg["POSTGRES_USER"], pg["POSTGRES_PASSWORD"], pg["POSTGRES_DB"])
    assert SERVICES["workbench"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    import psycopg  # the driver the URL names is installed

    assert psycopg.pq.version() >= 150000  # libpq of the binary wheel (PostgreSQL 15+ client)

    # the workbench reads these variable names (not only the CLI): Settings from the environment
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    settings = Settings()
    assert settings.url == env["DATABASE_URL"] and settings.scheduler == env["TISSUETWIN_SCHEDULER"]


def test_ports_match_the_dashboard_and_the_viewer():
    """--port P serves the dashboard on P and the viewer on P + 1 (serve_demo); both are
    exposed by the image, published on the host's loopback, and the health check asks P."""
    port = parse(SERVICES["workbench"]["command"]).port
    assert parse(exec_form(instructions("CMD")[0])).port == port
    exposed = {int(p) for args in instructions("EXPOSE") for p in args.split()}
    assert {port, port + 1} <= exposed
    published = {}
    for spec in SERVICES["workbench"]["ports"]:
        host_ip, host_port, container_port = spec.split(":")
        published[int(container_port)] = host_ip
    assert published == {port: "127.0.0.1", port + 1: "127.0.0.1"}
    health = " ".join(exec_form(instructions("HEALTHCHECK")[0]))
    assert f"http://127.0.0.1:{port}/api/health" in health
    from app.server.main import create_app

    assert "get" in create_app().openapi()["paths"]["/api/health"]


def test_image_installs_what_the_project_pins():
    args = dict(a.split("=", 1) for a in instructions("ARG") if "=" in a)
    assert args["PYTHON_IMAGE"] == "python:3.11-slim"
    assert args["TORCH_INDEX_URL"] == "https://download.pytorch.org/whl/cpu"
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    torch_pin = next(d for d in pyproject["project"]["dependencies"] if d.startswith("torch=="))
    runs = " ".join(instructions("RUN"))
    assert f"{torch_pin} " in f"{runs} " and '--index-url "${TORCH_INDEX_URL}"' in runs
    assert "libgomp1" in runs and "libusb-1.0-0" in runs  # what scripts/setup.sh installs for open3d
    assert re.search(r"pip install (-e )?\.", runs)


def test_dockerignore_keeps_what_the_image_copies():
    patterns = [p.strip().rstrip("/") for p in (ROOT / ".dockerignore").read_text().splitlines()
                if p.strip() and not p.startswith("#")]

    def ignored(name: str) -> bool:
        return any(fnmatch.fnmatch(name, p) for p in patterns)

    copied = []
    for args in instructions("COPY"):
        words = [w for w in args.split() if not w.startswith("--")]
        copied += words[:-1]
    assert copied and all((ROOT / c).exists() and not ignored(c) for c in copied), copied
    readme = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["readme"]
    assert readme in copied  # the build reads it
    for heavy in (".venv", ".git", "data", "tests"):
        assert ignored(heavy), heavy
