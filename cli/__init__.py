"""bcf: neural block-compressed features (BC6H) for PBR material texture sets.

The import package's sub-packages live in the repository's top-level folders: `bcf.core` (the library),
`bcf.engine` (shaders, GL, preview), `bcf.jobs` (queue, workers, batch, bench), `bcf.service` (HTTP API).
This folder holds the package root and the command-line interface.
"""

from bcf.core import __version__

__all__ = ["__version__"]
