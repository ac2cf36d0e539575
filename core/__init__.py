"""bcf.core: the library.

Data flows one way, one module per arrow:
files -> `material` (TextureSet) -> `training` (two-phase fit of the `model`, filtering in `sampling`, schedule
from `options`) -> `export` (DDS + decoder.bin + manifest, and the reference decoder that reads them back) ->
`metrics` / `report` (scores of the decoded files; `check` compares two reports). `compress` runs the whole pipeline and is what the CLI, jobs
and service call. Underneath: the BC6H codec (`bc6h`), texture containers (`containers`), image files and mip
chains (`images`), and BC6H texture tools (`bc6h_tools`).
"""
