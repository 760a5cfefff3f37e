"""The package's version, below every stage: a record names it
(:meth:`torchcf.runs.summary.Versions.current`) without importing the package
(``torchcf.__version__`` re-exports it)."""

__version__ = "0.1.0"

__all__ = ["__version__"]
