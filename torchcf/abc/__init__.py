"""The ABC engine (placeholder docstring, completed with the engine)."""
