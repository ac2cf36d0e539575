"""`bcf.core.material`: discovering a texture set's files by name, resolving explicit overrides, and loading them
into the (H, W, 8) material array. Real published names come from tests/data/material_names.json, real pixels
from tests/data/chainmail_128 and examples/sample; everything else is written small into tmp_path."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from bcf.core.material.images import read_image, read_rgb
from bcf.core.material.roles import CHANNELS, TEXTURES, MaterialError, MaterialFiles
from bcf.core.material.texture_set import TextureSet, load_material, load_texture_set
from bcf.core.material.naming import discover_material, resolve_material

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data"
SAMPLE = ROOT / "examples" / "sample"
CHAINMAIL = DATA / "chainmail_128"
NAMES = json.loads((DATA / "material_names.json").read_text())["materials"]
ROLE_KEYS = ("albedo", "normal", "arm", "ao", "roughness", "metalness")

# Sets whose normal map's name does not state its convention: discovery must say None (not guess), and loading
# assumes OpenGL with a note. Every other set's name states it (nor_gl, NormalGL, or ambientCG's DirectX `_Normal`).
CONVENTION_NOT_IN_NAME = {"StonePath007"}


# ------------------------------------------------------------------------------------------------ helpers


def write_image(path: Path, pixels: np.ndarray) -> Path:
    """Write (h, w, c) pixels with OpenImageIO, independently of bcf; uint8 stays 8-bit, floats stay float."""
    pixels = np.ascontiguousarray(pixels if pixels.ndim == 3 else pixels[..., None])
    height, width, channels = pixels.shape
    pixel_type = "uint8" if pixels.dtype == np.uint8 else "float"
    spec = oiio.ImageSpec(width, height, channels, pixel_type)
    # Store the given values: without this OIIO treats colour as premultiplied and divides it by alpha.
    spec.attribute("oiio:UnassociatedAlpha", 1)
    output = oiio.ImageOutput.create(str(path))
    assert output is not None, oiio.geterror()
    assert output.open(str(path), spec), output.geterror()
    assert output.write_image(pixels), output.geterror()
    output.close()
    return path


def oiio_pixels(path: Path) -> np.ndarray:
    """All channels of `path` as float32 in [0, 1], read with plain OpenImageIO (the test's own reference)."""
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # the stored values, not premultiplied by alpha
    image_input = oiio.ImageInput.open(str(path), config)
    spec = image_input.spec()
    pixels = image_input.read_image(0, 0, 0, spec.nchannels, "uint8")
    image_input.close()
    return pixels.reshape(spec.height, spec.width, spec.nchannels).astype(np.float32) / 255


def noise(width: int, height: int, channels: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, channels), dtype=np.uint8)


def make_set(folder: Path, size: tuple[int, int] = (64, 64), **overrides: tuple[int, int, int] | None) -> Path:
    """A complete set `albedo.png`, `normal_gl.png`, `rough.png` (w, h) in `folder`; `overrides` maps a file stem
    to (w, h, channels) to change one, or None to leave it out."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {"albedo": (*size, 3), "normal_gl": (*size, 3), "rough": (*size, 1), **overrides}
    for seed, (stem, shape) in enumerate(files.items()):
        if shape is not None:
            write_image(folder / f"{stem}.png", noise(*shape, seed=seed))
    return folder


def error_of(call, *args, **kwargs) -> str:
    """The message of the MaterialError `call` raises; it must be one line."""
    with pytest.raises(MaterialError) as caught:
        call(*args, **kwargs)
    message = str(caught.value)
    assert "\n" not in message, message
    return message


def names(paths) -> list[str]:
    return sorted(Path(p).name for p in paths)


# ------------------------------------------------------------------------------------- real file names


@pytest.fixture(scope="module")
def tiny_images(tmp_path_factory) -> dict[str, bytes]:
    """Bytes of a valid 64x64 RGB image per extension used in material_names.json."""
    folder = tmp_path_factory.mktemp("tiny")
    extensions = {Path(f).suffix.lower() for entry in NAMES.values() for f in entry["files"]}
    return {ext: write_image(folder / f"tiny{ext}", noise(64, 64, 3)).read_bytes() for ext in extensions}


def test_material_names_fixture_covers_the_reference_collection() -> None:
    assert len(NAMES) == 21
    for entry in NAMES.values():
        used = [entry[k] for k in ROLE_KEYS if k in entry] + entry["ignored"]
        assert sorted(used) == sorted(entry["files"])  # every published file has an expected role or is ignored


@pytest.mark.parametrize("material", sorted(NAMES))
def test_discovery_matches_index_on_real_names(material: str, tmp_path: Path, tiny_images: dict[str, bytes]) -> None:
    entry = NAMES[material]
    folder = tmp_path / material
    folder.mkdir()
    for file in entry["files"]:
        (folder / file).write_bytes(tiny_images[Path(file).suffix.lower()])

    found = discover_material(folder)

    assert {role: path.name for role, path in found.roles().items()} == {k: entry[k] for k in ROLE_KEYS if k in entry}
    assert names(found.ignored) == sorted(entry["ignored"])
    if material in CONVENTION_NOT_IN_NAME:
        assert found.normal_convention is None
    else:
        assert found.normal_convention == entry["normal_convention"]

    # The same folder loads, with index.json's constants for the maps a set lacks.
    texture_set = load_material(folder)
    assert texture_set.channels.shape == (64, 64, 8)
    assert texture_set.source.name == material
    assert texture_set.source.normal_convention == entry["normal_convention"]
    assert texture_set.source.arm_packed == ("arm" in entry)
    expected_defaults = {} if "arm" in entry else \
        {role: value for role, value in (("ao", 1.0), ("metalness", 0.0)) if role not in entry}
    assert texture_set.source.defaults == expected_defaults
    if material in CONVENTION_NOT_IN_NAME:
        assert any("assuming OpenGL" in note and "normal convention" in note for note in texture_set.notes)


def test_ambientcg_plain_normal_is_directx_with_a_note(tmp_path: Path, tiny_images: dict[str, bytes]) -> None:
    for file in NAMES["Metal009"]["files"]:
        (tmp_path / file).write_bytes(tiny_images[".jpg"])
    found = discover_material(tmp_path)
    assert found.normal_convention == "directx"
    assert any("Metal009_2K_Normal.jpg" in note and "normal convention" in note for note in found.notes)
    # An explicit convention settles it: no note, and the user's value is used.
    resolved = resolve_material(tmp_path, MaterialFiles(normal_convention="opengl"))
    assert resolved.normal_convention == "opengl"
    assert not any("_Normal" in note for note in resolved.notes)


@pytest.mark.parametrize("stems, expected", [
    # generic exporters, glTF ORM
    (["Brick_BaseColor", "Brick_Normal_OpenGL", "T_Brick_ORM"], {"albedo": 0, "normal": 1, "arm": 2}),
    (["wall_base_color", "wall_normal_dx", "wall_Roughness", "wall_Metallic", "wall_AO"],
     {"albedo": 0, "normal": 1, "roughness": 2, "metalness": 3, "ao": 4}),
    # A material name containing a role word must not make every file that role: only the end of the name counts.
    (["rusty_metal_02_diff_2k", "rusty_metal_02_nor_gl_2k", "rusty_metal_02_rough_2k", "rusty_metal_02_metal_2k"],
     {"albedo": 0, "normal": 1, "roughness": 2, "metalness": 3}),
    # Case, resolution/format noise and separators do not matter.
    (["ROCK_ALBEDO_4K", "rock normal gl 4k", "rock.roughness.4k", "rock-Displacement-4K"],
     {"albedo": 0, "normal": 1, "roughness": 2}),
])
def test_discovery_of_common_names(tmp_path: Path, stems: list[str], expected: dict[str, int]) -> None:
    for stem in stems:
        write_image(tmp_path / f"{stem}.png", noise(64, 64, 3))
    found = discover_material(tmp_path)
    assert {role: path.stem for role, path in found.roles().items()} == {r: stems[i] for r, i in expected.items()}
    assert names(found.ignored) == sorted(f"{s}.png" for i, s in enumerate(stems) if i not in expected.values())


# -------------------------------------------------------------------------------------- bundled sample


def test_sample_is_discovered() -> None:
    found = discover_material(SAMPLE)
    assert {role: path.name for role, path in found.roles().items()} == \
        {"albedo": "albedo.png", "normal": "normal_gl.png", "arm": "arm.png"}
    assert found.normal_convention == "opengl"
    assert names(found.ignored) == ["LICENSE.md"]
    assert found.notes == []


def test_sample_loads_as_stored() -> None:
    texture_set = load_material(SAMPLE)
    channels = texture_set.channels
    assert isinstance(texture_set, TextureSet)
    assert channels.shape == (256, 256, len(CHANNELS)) and channels.dtype == np.float32
    assert (texture_set.width, texture_set.height) == (256, 256)
    assert 0.0 <= channels.min() and channels.max() <= 1.0
    # Each texture lands where TEXTURES says, values exactly as stored (no flip, no colour conversion).
    np.testing.assert_allclose(channels[..., TEXTURES["albedo"]], oiio_pixels(SAMPLE / "albedo.png"), atol=1e-6)
    np.testing.assert_allclose(channels[..., TEXTURES["normal"]], oiio_pixels(SAMPLE / "normal_gl.png")[..., :2],
                               atol=1e-6)
    # ARM packing R, G, B = AO, roughness, metalness = channels 5, 6, 7.
    assert CHANNELS[5:8] == ("ao", "roughness", "metalness")
    np.testing.assert_allclose(channels[..., TEXTURES["arm"]], oiio_pixels(SAMPLE / "arm.png"), atol=1e-6)

    source = texture_set.source
    assert (source.name, source.width, source.height) == ("sample", 256, 256)
    assert source.normal_convention == "opengl" and source.arm_packed and source.defaults == {}
    assert [(f.role, f.name, f.channels, f.format, f.bits) for f in source.files] == [
        ("albedo", "albedo.png", 3, "png", "uint8"), ("normal", "normal_gl.png", 3, "png", "uint8"),
        ("arm", "arm.png", 3, "png", "uint8")]
    for file in source.files:
        assert file.sha256 == hashlib.sha256((SAMPLE / file.name).read_bytes()).hexdigest()
        assert (file.width, file.height) == (256, 256)
    assert texture_set.notes == ()
    json.loads(source.model_dump_json())  # the manifest entry serialises


# -------------------------------------------------------------------------------------- chainmail crop


def test_chainmail_discovery() -> None:
    found = discover_material(CHAINMAIL)
    assert {role: path.name for role, path in found.roles().items()} == {
        "albedo": "Chainmail004_1K_Color.png", "normal": "Chainmail004_1K_Normal.png",
        "roughness": "Chainmail004_1K_Roughness.png", "metalness": "Chainmail004_1K_Metalness.png"}
    assert found.normal_convention == "directx"
    assert names(found.ignored) == ["Chainmail004_1K_Displacement.png", "Chainmail004_1K_Opacity.png", "LICENSE.md"]


def test_chainmail_loads_with_ao_default() -> None:
    texture_set = load_material(CHAINMAIL)
    channels = texture_set.channels
    assert channels.shape == (128, 128, 8) and channels.dtype == np.float32
    assert 0.0 <= channels.min() and channels.max() <= 1.0
    assert texture_set.source.defaults == {"ao": 1.0}
    assert np.all(channels[..., 5] == 1.0)
    assert any(note.startswith("no ao map") for note in texture_set.notes)
    # The DirectX normal is kept as stored: not flipped to OpenGL.
    assert texture_set.source.normal_convention == "directx"
    np.testing.assert_allclose(channels[..., 3:5], oiio_pixels(CHAINMAIL / "Chainmail004_1K_Normal.png")[..., :2],
                               atol=1e-6)
    np.testing.assert_allclose(channels[..., 6], oiio_pixels(CHAINMAIL / "Chainmail004_1K_Roughness.png")[..., 0],
                               atol=1e-6)
    np.testing.assert_allclose(channels[..., 7], oiio_pixels(CHAINMAIL / "Chainmail004_1K_Metalness.png")[..., 0],
                               atol=1e-6)
    assert [f.channels for f in texture_set.source.files] == [3, 3, 1, 1]


def test_missing_metalness_defaults_to_zero(tmp_path: Path) -> None:
    for file in CHAINMAIL.glob("*.png"):
        if "Metalness" not in file.name:
            shutil.copy(file, tmp_path / file.name)
    texture_set = load_material(tmp_path)
    assert texture_set.source.defaults == {"ao": 1.0, "metalness": 0.0}
    assert np.all(texture_set.channels[..., 7] == 0.0) and np.all(texture_set.channels[..., 5] == 1.0)
    assert any(note.startswith("no metalness map") for note in texture_set.notes)


# ------------------------------------------------------------------------------------------------ errors


def test_nonexistent_folder(tmp_path: Path) -> None:
    message = error_of(load_material, tmp_path / "nope")
    assert str(tmp_path / "nope") in message and "no such folder" in message


def test_not_a_folder(tmp_path: Path) -> None:
    file = write_image(tmp_path / "albedo.png", noise(64, 64, 3))
    message = error_of(discover_material, file)
    assert str(file) in message and "not a folder" in message


def test_empty_folder(tmp_path: Path) -> None:
    message = error_of(load_material, tmp_path)
    assert str(tmp_path) in message and "no files" in message


def test_missing_normal(tmp_path: Path) -> None:
    make_set(tmp_path, normal_gl=None)
    message = error_of(load_material, tmp_path)
    assert str(tmp_path) in message
    assert "albedo albedo.png" in message and "roughness rough.png" in message  # what was found
    # Options are named as the models spell them; the CLI words them as flags, the service as form fields.
    assert "missing normal" in message and "albedo/normal/arm/roughness" in message


def test_missing_roughness_mentions_arm(tmp_path: Path) -> None:
    make_set(tmp_path, rough=None)
    message = error_of(load_material, tmp_path)
    assert "missing roughness (or an ARM map)" in message


def test_folder_without_images_is_incomplete(tmp_path: Path) -> None:
    (tmp_path / "readme.txt").write_text("hello")
    message = error_of(load_material, tmp_path)
    assert "found nothing" in message and "missing albedo, normal, roughness" in message


@pytest.mark.parametrize("first, second", [("x_diff_1k", "x_col_1k"), ("x_diff_1k", "x_diff_2k")])
def test_two_albedo_candidates(tmp_path: Path, first: str, second: str) -> None:
    make_set(tmp_path, albedo=None)
    for stem in (first, second):
        write_image(tmp_path / f"{stem}.png", noise(64, 64, 3))
    message = error_of(discover_material, tmp_path)
    assert f"{first}.png" in message and f"{second}.png" in message and "name it with albedo" in message
    # Naming the albedo explicitly settles it.
    resolved = resolve_material(tmp_path, MaterialFiles(albedo=tmp_path / f"{first}.png"))
    assert resolved.albedo == tmp_path / f"{first}.png"
    assert tmp_path / f"{second}.png" in resolved.ignored and tmp_path / f"{first}.png" not in resolved.ignored


def test_two_opengl_normals(tmp_path: Path) -> None:
    make_set(tmp_path)
    write_image(tmp_path / "x_nor_gl_2k.png", noise(64, 64, 3))
    message = error_of(discover_material, tmp_path)
    assert "normal_gl.png" in message and "x_nor_gl_2k.png" in message


def test_mismatched_sizes(tmp_path: Path) -> None:
    make_set(tmp_path, normal_gl=(128, 128, 3), rough=(64, 128, 1))
    message = error_of(load_material, tmp_path)
    for part in ("albedo.png 64x64", "normal_gl.png 128x128", "rough.png 64x128", "differ in size"):
        assert part in message, message


@pytest.mark.parametrize("size", [(96, 96), (32, 32), (128, 48)])
def test_unsupported_size(tmp_path: Path, size: tuple[int, int]) -> None:
    make_set(tmp_path, size=size)
    message = error_of(load_material, tmp_path)
    assert "albedo.png" in message and f"{size[0]}x{size[1]}" in message and "power of two" in message


def test_non_square_power_of_two_is_fine(tmp_path: Path) -> None:
    make_set(tmp_path, size=(128, 64))
    texture_set = load_material(tmp_path)
    assert texture_set.channels.shape == (64, 128, 8) and (texture_set.width, texture_set.height) == (128, 64)


def test_unreadable_file(tmp_path: Path) -> None:
    make_set(tmp_path, albedo=None)
    (tmp_path / "albedo.png").write_bytes(b"this is not a png at all" * 10)
    message = error_of(load_material, tmp_path)
    assert str(tmp_path / "albedo.png") in message and "cannot read" in message


def test_truncated_file(tmp_path: Path) -> None:
    make_set(tmp_path)
    data = (tmp_path / "albedo.png").read_bytes()
    (tmp_path / "albedo.png").write_bytes(data[: len(data) // 2])
    message = error_of(load_material, tmp_path)
    assert str(tmp_path / "albedo.png") in message and "cannot read" in message


@pytest.mark.parametrize("stem, channels, expected", [
    ("albedo", 1, "albedo needs 3 channels (RGB), found 1"),
    ("albedo", 2, "albedo needs 3 channels (RGB), found 2"),
    ("normal_gl", 1, "normal needs 2 or 3 channels (XY or XYZ), found 1"),
    ("rough", 2, "roughness needs 1 channel (grey) or 3 (RGB, R is used), found 2"),
])
def test_wrong_channel_count(tmp_path: Path, stem: str, channels: int, expected: str) -> None:
    make_set(tmp_path, **{stem: (64, 64, channels)})
    message = error_of(load_material, tmp_path)
    assert message == f"{tmp_path / (stem + '.png')}: {expected}"


def test_arm_file_needs_three_channels(tmp_path: Path) -> None:
    make_set(tmp_path, rough=None, arm=(64, 64, 1))
    assert "arm needs 3 channels" in error_of(load_material, tmp_path)


def test_explicit_arm_with_roughness(tmp_path: Path) -> None:
    make_set(tmp_path, arm=(64, 64, 3))
    explicit = MaterialFiles(arm=tmp_path / "arm.png", roughness=tmp_path / "rough.png")
    message = error_of(load_material, tmp_path, explicit)
    assert "arm.png" in message and "arm cannot be combined with roughness" in message
    assert "arm cannot be combined" in error_of(resolve_material, None, explicit)


def test_explicit_file_missing(tmp_path: Path) -> None:
    make_set(tmp_path)
    message = error_of(load_material, tmp_path, MaterialFiles(normal=tmp_path / "other_normal.png"))
    assert "other_normal.png" in message and "given as normal" in message


def test_load_texture_set_checks_completeness(tmp_path: Path) -> None:
    make_set(tmp_path)
    message = error_of(load_texture_set, MaterialFiles(albedo=tmp_path / "albedo.png", normal=tmp_path / "normal_gl.png"))
    assert str(tmp_path) in message and "missing roughness" in message


def test_nan_values(tmp_path: Path) -> None:
    make_set(tmp_path, rough=None)
    rough = np.full((64, 64, 1), 0.5, np.float32)
    rough[0, 0] = np.nan
    write_image(tmp_path / "rough.exr", rough)
    message = error_of(load_material, tmp_path)
    assert "rough.exr" in message and "1 values are NaN" in message


# ----------------------------------------------------------------------------- choices and notes


def test_opengl_and_directx_normals_use_opengl(tmp_path: Path) -> None:
    make_set(tmp_path, normal_gl=None)
    write_image(tmp_path / "x_nor_gl_1k.png", noise(64, 64, 3, seed=1))
    write_image(tmp_path / "x_nor_dx_1k.png", noise(64, 64, 3, seed=2))
    found = discover_material(tmp_path)
    assert found.normal.name == "x_nor_gl_1k.png" and found.normal_convention == "opengl"
    assert names(found.ignored) == ["x_nor_dx_1k.png"]
    assert any("both OpenGL and DirectX" in note for note in found.notes)
    # Asking for DirectX takes the DirectX file instead.
    resolved = resolve_material(tmp_path, MaterialFiles(normal_convention="directx"))
    assert resolved.normal.name == "x_nor_dx_1k.png" and resolved.normal_convention == "directx"


def test_arm_wins_over_separate_maps(tmp_path: Path) -> None:
    make_set(tmp_path, arm=(64, 64, 3), ao=(64, 64, 1))
    found = discover_material(tmp_path)
    assert found.arm.name == "arm.png" and found.roughness is None and found.ao is None
    assert names(found.ignored) == ["ao.png", "rough.png"]
    assert any("using the ARM map arm.png" in note for note in found.notes)
    texture_set = load_material(tmp_path)
    assert texture_set.source.arm_packed and texture_set.source.defaults == {}
    assert any("using the ARM map" in note for note in texture_set.notes)  # discovery notes reach the caller


def test_explicit_roughness_replaces_discovered_arm(tmp_path: Path) -> None:
    make_set(tmp_path, rough=None, arm=(64, 64, 3))
    write_image(tmp_path / "other.png", noise(64, 64, 1, seed=9))
    resolved = resolve_material(tmp_path, MaterialFiles(roughness=tmp_path / "other.png"))
    assert resolved.arm is None and resolved.roughness == tmp_path / "other.png"
    assert any("ignoring arm.png: roughness maps given explicitly" == note for note in resolved.notes)
    texture_set = load_texture_set(resolved)
    np.testing.assert_allclose(texture_set.channels[..., 6], oiio_pixels(tmp_path / "other.png")[..., 0], atol=1e-6)
    assert texture_set.source.defaults == {"ao": 1.0, "metalness": 0.0}


def test_explicit_files_without_folder(tmp_path: Path) -> None:
    make_set(tmp_path)
    (tmp_path / "normal_gl.png").rename(tmp_path / "n.png")
    explicit = MaterialFiles(albedo=tmp_path / "albedo.png", normal=tmp_path / "n.png",
                             roughness=tmp_path / "rough.png")
    texture_set = load_material(None, explicit)
    assert texture_set.source.name == "albedo"  # the albedo file's stem
    assert texture_set.source.normal_convention == "opengl"
    assert any("n.png" in note and "assuming OpenGL" in note and "normal convention to directx" in note
               for note in texture_set.notes)
    # A convention in the explicit normal's name is used; an explicit convention beats it.
    (tmp_path / "n.png").rename(tmp_path / "n_nor_dx.png")
    explicit = explicit.model_copy(update={"normal": tmp_path / "n_nor_dx.png"})
    assert resolve_material(None, explicit).normal_convention == "directx"
    explicit = explicit.model_copy(update={"normal_convention": "opengl"})
    assert resolve_material(None, explicit).normal_convention == "opengl"


def test_albedo_alpha_is_ignored_and_not_premultiplied(tmp_path: Path) -> None:
    make_set(tmp_path, albedo=None)
    rgba = noise(64, 64, 4)
    rgba[..., 3] = 0  # fully transparent: premultiplying would zero the colour
    write_image(tmp_path / "albedo.png", rgba)
    texture_set = load_material(tmp_path)
    np.testing.assert_allclose(texture_set.channels[..., :3], rgba[..., :3] / 255, atol=1e-6)
    assert any("albedo.png: albedo alpha channel ignored" == note for note in texture_set.notes)


def test_two_channel_normal(tmp_path: Path) -> None:
    make_set(tmp_path, normal_gl=(64, 64, 2))
    texture_set = load_material(tmp_path)
    np.testing.assert_allclose(texture_set.channels[..., 3:5], oiio_pixels(tmp_path / "normal_gl.png"), atol=1e-6)


def test_rgb_roughness_uses_red_and_notes_differences(tmp_path: Path) -> None:
    make_set(tmp_path, rough=None)
    grey = np.repeat(noise(64, 64, 1, seed=4), 3, axis=2)
    write_image(tmp_path / "rough.png", grey)
    assert not any("differing" in note for note in load_material(tmp_path).notes)  # grey stored as RGB: silent
    coloured = grey.copy()
    coloured[..., 1] = 255 - coloured[..., 0]
    write_image(tmp_path / "rough.png", coloured)
    texture_set = load_material(tmp_path)
    np.testing.assert_allclose(texture_set.channels[..., 6], coloured[..., 0] / 255, atol=1e-6)
    assert any(re.match(r"rough\.png: roughness stored as RGB with differing channels", n) for n in texture_set.notes)


def test_float_values_are_clipped_with_a_count(tmp_path: Path) -> None:
    make_set(tmp_path, rough=None)
    rough = np.full((64, 64, 1), 0.25, np.float32)
    rough[0, :5] = 1.5
    rough[1, :2] = -0.5
    write_image(tmp_path / "rough.exr", rough)
    texture_set = load_material(tmp_path)
    assert texture_set.channels[..., 6].min() == 0.0 and texture_set.channels[..., 6].max() == 1.0
    assert "rough.exr: 7 values outside [0, 1] clipped" in texture_set.notes
    assert [(f.format, f.bits) for f in texture_set.source.files if f.role == "roughness"] == [("openexr", "float")]


@pytest.mark.parametrize("convention, flagged", [("directx", False), ("opengl", True)])
def test_a_normal_map_read_with_the_wrong_convention_gets_a_note(convention: str, flagged: bool) -> None:
    """Chainmail004's map is DirectX: read as OpenGL its slopes are far from a height map's, and the user is told
    (its name says DirectX, so the explicit convention is what a user who got it wrong would pass)."""
    texture_set = load_material(CHAINMAIL, MaterialFiles(normal_convention=convention))
    notes = [n for n in texture_set.notes if "looks like DirectX (Y-)" in n]
    assert len(notes) == int(flagged), texture_set.notes
    if flagged:
        assert notes[0].startswith("Chainmail004_1K_Normal.png:") and "set the normal convention to directx" in notes[0]


def test_a_correctly_labelled_normal_map_gets_no_convention_note() -> None:
    assert not [n for n in load_material(SAMPLE).notes if "looks like" in n]


def test_an_exr_albedo_is_noted_as_linear(tmp_path: Path) -> None:
    make_set(tmp_path, albedo=None)
    write_image(tmp_path / "albedo.exr", noise(64, 64, 3, seed=7))
    notes = load_material(tmp_path).notes
    assert any(n.startswith("albedo.exr: albedo in OpenEXR, which is linear by convention") for n in notes), notes


# ------------------------------------------------------------------------------------------- images.py


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_read_image_keeps_every_channel(tmp_path: Path, channels: int) -> None:
    pixels = noise(64, 32, channels)
    path = write_image(tmp_path / "x.png", pixels)
    image = read_image(path)
    assert image.shape == (32, 64, channels) and image.dtype == np.float32
    np.testing.assert_allclose(image, pixels / 255, atol=1e-6)
    assert read_rgb(path).shape == (32, 64, 3)
