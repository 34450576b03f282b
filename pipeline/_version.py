"""The package's version, in the lowest layer so that every module (the file writer, the
exporters, the batch cache) can stamp it without importing the package root."""

__version__ = "0.1.0"
