"""The package version (one place: the report, the CLI and packaging read it)."""

__version__ = "0.1.0"
