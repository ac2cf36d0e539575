"""bcf.core.fit: texture set -> trained neural material (paper §3-5).

`sampling` (texture filtering, the reference pyramid F(M)), `block_decode` (the differentiable BC6H decode,
eq. 7-9), `model` (feature pyramids and the MLP), `training` (the two-phase fit).
"""
