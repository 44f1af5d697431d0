"""The SDK version (also its distribution version, read by setuptools)."""

__version__ = "0.1.0"
