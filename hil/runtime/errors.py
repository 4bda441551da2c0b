"""Errors every command may meet, in a module light enough for ``hil.cli`` to import at start."""

from __future__ import annotations


class WorkerError(RuntimeError):
    """A worker process (``hil sim``'s tail, ``hil rerun``'s cores) failed or died; the message
    says which, and holds the worker's traceback when it raised."""
