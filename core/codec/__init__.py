"""bcf.core.codec: BC6H as a format, knowing nothing of materials or training.

`bc6h` (the mode tables, bit-exact decode and encode of all 14 modes), `partition` (partition
search and block fitting), `containers` (DDS and KTX2 files), `textures` (whole mipmapped textures: encode,
verify, describe). numpy only: no torch.
"""
