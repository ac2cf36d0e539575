"""bcf: neural block-compressed features (BC6H) for PBR material texture sets.

The import package's sub-packages live in the repository's top-level folders:
`bcf.core` (training and export library), `bcf.jobs` (queue and workers), `bcf.service` (HTTP API).
This folder holds the package root and the command-line interface.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("bcf")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
