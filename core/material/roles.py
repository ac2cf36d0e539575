"""The roles table: which texture maps a material has, which of the 8 channels each fills, the constants for
maps a material may lack, and the conversion of decoded channels back to texture images.

Values are kept as stored: albedo stays sRGB-encoded, the normal's x and y stay (n + 1) / 2 in the source's
convention, AO, roughness and metalness are linear [0, 1].
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, get_args

import numpy as np
import pydantic

from bcf.core.errors import InputError

Role = Literal["albedo", "normal", "arm", "ao", "roughness", "metalness"]
NormalConvention = Literal["opengl", "directx"]
# Maps bcf does not compress but an asset scan still lists with their material (`bcf.core.material.assets`).
ExtraRole = Literal["height", "opacity"]

ROLES: tuple[Role, ...] = get_args(Role)
# The maps an ARM (or glTF ORM) texture packs, in its channel order R, G, B.
PACKED_ROLES: tuple[Role, ...] = ("ao", "roughness", "metalness")

CHANNELS = ("albedo_r", "albedo_g", "albedo_b", "normal_x", "normal_y", "ao", "roughness", "metalness")
# Where each texture of the compressed material lives in the channel axis of `TextureSet.channels`.
TEXTURES: dict[str, slice] = {"albedo": slice(0, 3), "normal": slice(3, 5), "arm": slice(5, 8)}
CHANNEL_OF: dict[Role, int] = {"ao": 5, "roughness": 6, "metalness": 7}

# Constants for maps a material may lack: no AO means nothing is occluded, no metalness means a dielectric.
DEFAULTS: dict[Role, float] = {"ao": 1.0, "metalness": 0.0}

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".tga", ".tif", ".tiff", ".exr"})
MIN_SIZE = 64


class MaterialError(InputError):
    """Bad material input: the file (or folder) at fault, the role, and the problem."""


# ------------------------------------------------------------------------------------------------ models


class MaterialFiles(pydantic.BaseModel):
    """Which file plays which role. `arm` and the separate `ao`/`roughness`/`metalness` exclude each other."""

    model_config = pydantic.ConfigDict(extra="forbid")

    albedo: Path | None = pydantic.Field(None, description="base colour (sRGB-encoded RGB)")
    normal: Path | None = pydantic.Field(None, description="tangent-space normal map (x, y used; z rebuilt)")
    arm: Path | None = pydantic.Field(None, description="packed AO (R), roughness (G), metalness (B)")
    ao: Path | None = pydantic.Field(None, description="ambient occlusion, grey (default: 1)")
    roughness: Path | None = pydantic.Field(None, description="roughness, grey")
    metalness: Path | None = pydantic.Field(None, description="metalness, grey (default: 0)")
    normal_convention: NormalConvention | None = None  # None: unknown (load assumes opengl and adds a note)
    ignored: list[Path] = []  # files found in the folder that play no role (height, opacity, ...)
    notes: list[str] = []  # choices discovery made, to show the user

    def roles(self) -> dict[Role, Path]:
        """The roles that have a file, in `ROLES` order."""
        return {role: path for role in ROLES if (path := getattr(self, role)) is not None}


def material_images(channels: np.ndarray) -> dict[str, np.ndarray]:
    """(h, w, 8) decoded material -> albedo, normal (z rebuilt), ARM as (h, w, 3) images in [0, 1]."""
    channels = np.clip(channels, 0.0, 1.0)
    xy = channels[..., 3:5] * 2.0 - 1.0
    z = np.sqrt(np.clip(1.0 - (xy**2).sum(-1, keepdims=True), 0.0, 1.0))
    return {"albedo": channels[..., 0:3], "normal": np.concatenate([channels[..., 3:5], (z + 1.0) / 2.0], -1),
            "arm": channels[..., 5:8]}
