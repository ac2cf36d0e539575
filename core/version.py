"""The installed bcf version: manifests, reports and summaries record it as their generator."""

from importlib.metadata import PackageNotFoundError, version

__all__ = ["GENERATOR", "__version__"]

try:
    __version__ = version("bcf")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

GENERATOR = f"bcf {__version__}"
