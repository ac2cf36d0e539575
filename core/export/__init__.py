"""bcf.core.export: trained model -> exported artifacts, and the one reference decoder that reads them back.

`artifacts` (the files docs/FORMAT.md specifies: feature textures, decoder.bin, manifest.json; writing them),
`decode` (an export folder -> a decoder evaluated at any (u, v, s), and decoded images).
"""
