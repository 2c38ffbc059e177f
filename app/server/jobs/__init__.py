"""Jobs: the registry of job types, what a running job sees, and the runner on Dask."""

from app.server.jobs.context import JobCancelled, JobContext, LocalChannel, WorkerCrashed
from app.server.jobs.registry import JobType, Registry

__all__ = ["JobCancelled", "JobContext", "LocalChannel", "WorkerCrashed", "JobType", "Registry"]
