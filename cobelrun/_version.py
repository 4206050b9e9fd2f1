"""The package version, in a module of its own so the library can name it without importing
the package root (``cobelrun/__init__.py``, a facade over the orchestration-level API)."""

__version__ = "0.1.0"
