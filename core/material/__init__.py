"""bcf.core.material: files -> texture set.

`images` (image files <-> float arrays, box-filtered mip chains), `roles` (the roles table: maps, channels,
defaults), `naming` (which file plays which role, from its name), `texture_set` (loading and validation into
the (H, W, 8) `TextureSet`), `assets` (a whole asset tree -> the texture sets in it).
"""
