"""Close the loop (placeholder, split in progress)."""

from .loop import DiagnoseError, diagnose_run, main  # noqa: F401
