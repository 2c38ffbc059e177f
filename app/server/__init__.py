"""The workbench's job service: FastAPI routes, SQLAlchemy persistence, jobs on Dask.

    from app.server.main import create_app
    from app.server.settings import Settings
    app = create_app(Settings(data_dir="data"))     # uvicorn.run(app, host=..., port=...)

Layout (full-stack-fastapi-template): ``settings`` (pydantic-settings), ``db`` (models
and engine), ``jobs`` (registry of job types and the runner), ``services`` (what the
routes call), ``api/routes`` (one router per resource), ``errors`` (domain errors to
HTTP, in one place), ``main`` (the app factory).
"""

# Nothing imported here: Dask workers import app.server.jobs without FastAPI or viser.
