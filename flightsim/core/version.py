"""The package version, importable from any layer (the package root imports the API)."""

__version__ = "0.1.0"
