"""`bcf.core.assets`: scanning an asset library (a folder tree) into materials for `bcf batch`. Real published
names come from tests/data/material_names.json; the images are tiny files written into tmp_path (their size only
matters for `resolution`, and for the one set that is loaded)."""

from __future__ import annotations

import json
from pathlib import Path

import OpenImageIO as oiio
import pytest

from bcf.core.material.assets import AssetScan, FoundMaterial, scan_assets
from bcf.core.material.roles import IMAGE_EXTENSIONS, MaterialError
from bcf.core.material.naming import discover_material, normal_convention_from_name
from bcf.core.material.texture_set import load_texture_set

DATA = Path(__file__).resolve().parent / "data"
NAMES = json.loads((DATA / "material_names.json").read_text())["materials"]
COMPRESSED_ROLES = ("albedo", "normal", "arm", "ao", "roughness", "metalness")
# Sets whose normal map's name does not state its convention (see tests/test_material.py).
CONVENTION_NOT_IN_NAME = {"StonePath007"}
# The words that make an unused map one the scan lists with its material (the test's own table).
EXTRA_WORDS = {"displacement": "height", "height": "height", "opacity": "opacity"}


# ------------------------------------------------------------------------------------------------ helpers


def write_image(path: Path, size: tuple[int, int] = (8, 8), channels: int = 3) -> Path:
    """A black image of `size` (width, height); the format follows the extension."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert oiio.ImageBuf(oiio.ImageSpec(size[0], size[1], channels, oiio.UINT8)).write(str(path)), oiio.geterror()
    return path


def make_folder(folder: Path, names: list[str], size: tuple[int, int] = (8, 8)) -> Path:
    """Tiny images under the given names in `folder`; names that are not images become empty files."""
    for name in names:
        if Path(name).suffix.lower() in IMAGE_EXTENSIONS:
            write_image(folder / name, size)
        else:
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(b"")
    return folder


def by_output(scan: AssetScan) -> dict[str, FoundMaterial]:
    return {found.output: found for found in scan.materials}


def names_of(found: FoundMaterial) -> dict[str, str]:
    """role -> file name (no folder)."""
    return {role: Path(path).name for role, path in found.files.items()}


def unplaced(scan: AssetScan) -> dict[str, str]:
    return {entry.path: entry.reason for entry in scan.unplaced}


# -------------------------------------------------------------------------------- the 21 reference sets


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> tuple[Path, AssetScan]:
    """All 21 reference sets, one folder each under one root, albedos 16x8 and the rest 8x8, scanned once."""
    root = tmp_path_factory.mktemp("library")
    for name, entry in NAMES.items():
        make_folder(root / name, [file for file in entry["files"] if file != entry["albedo"]])
        write_image(root / name / entry["albedo"], (16, 8))
    return root, scan_assets(root)


def test_reference_library_has_21_complete_materials(library: tuple[Path, AssetScan]) -> None:
    _, scan = library
    assert sorted(found.output for found in scan.materials) == sorted(NAMES)
    assert scan.unplaced == []
    for found in scan.materials:
        assert found.problems == [], (found.material, found.problems)
        assert found.material == found.dir == found.output
        assert found.resolution == (16, 8)


@pytest.mark.parametrize("name", sorted(NAMES))
def test_reference_set_roles(library: tuple[Path, AssetScan], name: str) -> None:
    root, scan = library
    entry = NAMES[name]
    found = by_output(scan)[name]
    extras = {EXTRA_WORDS[word]: file for file in entry["ignored"] for word in EXTRA_WORDS if word in file.lower()}
    assert len(extras) == len(entry["ignored"])  # every ignored file of the collection is a height or opacity map
    expected = {role: entry[role] for role in COMPRESSED_ROLES if role in entry} | extras
    assert names_of(found) == expected
    assert all(path == f"{name}/{Path(path).name}" for path in found.files.values())
    if name in CONVENTION_NOT_IN_NAME:
        assert found.normal_convention is None
    else:
        assert found.normal_convention == entry["normal_convention"]
    # The same choices and notes as `bcf compress FOLDER` (e.g. ambientCG's DirectX `_Normal` note).
    discovered = discover_material(root / name)
    assert found.notes == discovered.notes
    assert {role: path.name for role, path in discovered.roles().items()} == \
        {role: file for role, file in expected.items() if role in COMPRESSED_ROLES}


def test_material_files_are_absolute_for_every_reference_set(library: tuple[Path, AssetScan]) -> None:
    root, scan = library
    for found in scan.materials:
        files = found.material_files(root)
        assert {role: path for role, path in files.roles().items()} == \
            {role: (root / path).resolve() for role, path in found.files.items() if role in COMPRESSED_ROLES}
        assert all(path.is_absolute() and path.is_file() for path in files.roles().values())
        assert files.normal_convention == found.normal_convention


# ------------------------------------------------------------------------------------ naming conventions


def test_substance_painter_folder_with_two_materials(tmp_path: Path) -> None:
    make_folder(tmp_path / "export", [
        "Wood_BaseColor.png", "Wood_Normal_OpenGL.png", "Wood_OcclusionRoughnessMetallic.png",
        "Metal_BaseColor.png", "Metal_Normal_OpenGL.png", "Metal_OcclusionRoughnessMetallic.png",
        "Metal_Emissive.png",
    ])
    scan = scan_assets(tmp_path)
    assert sorted(by_output(scan)) == ["export/Metal", "export/Wood"]
    for prefix in ("Wood", "Metal"):
        found = by_output(scan)[f"export/{prefix}"]
        assert found.material == f"export/{prefix}" and found.dir == "export"
        assert found.files == {"albedo": f"export/{prefix}_BaseColor.png",
                               "normal": f"export/{prefix}_Normal_OpenGL.png",
                               "arm": f"export/{prefix}_OcclusionRoughnessMetallic.png"}
        assert found.normal_convention == "opengl" and found.problems == [] and found.notes == []
    assert scan.unplaced == []  # the emissive map is a known unused map: neither listed nor unplaced


def test_substance_painter_separate_maps(tmp_path: Path) -> None:
    make_folder(tmp_path, ["Rock_BaseColor.png", "Rock_Normal_DirectX.png", "Rock_Roughness.png",
                           "Rock_Metallic.png", "Rock_Mixed_AO.png", "Rock_Height.png", "Rock_Opacity.png"])
    (found,) = scan_assets(tmp_path).materials
    assert names_of(found) == {"albedo": "Rock_BaseColor.png", "normal": "Rock_Normal_DirectX.png",
                               "ao": "Rock_Mixed_AO.png", "roughness": "Rock_Roughness.png",
                               "metalness": "Rock_Metallic.png", "height": "Rock_Height.png",
                               "opacity": "Rock_Opacity.png"}
    assert found.normal_convention == "directx" and found.problems == []


def test_substance_painter_plain_normal_convention_is_unknown(tmp_path: Path) -> None:
    # Substance's plain `_Normal` is OpenGL or DirectX depending on the export preset: the name does not tell.
    make_folder(tmp_path, ["Rock_BaseColor.png", "Rock_Normal.png", "Rock_OcclusionRoughnessMetallic.png"])
    (found,) = scan_assets(tmp_path).materials
    assert found.normal_convention is None and found.problems == []


def test_unreal_names(tmp_path: Path) -> None:
    make_folder(tmp_path / "T_Brick", ["T_Brick_D.png", "T_Brick_N.png", "T_Brick_ORM.png"])
    make_folder(tmp_path / "T_Tile", ["T_Tile_BC.png", "T_Tile_N.png", "T_Tile_ORM.png"])
    scan = scan_assets(tmp_path)
    brick, tile = by_output(scan)["T_Brick"], by_output(scan)["T_Tile"]
    assert names_of(brick) == {"albedo": "T_Brick_D.png", "normal": "T_Brick_N.png", "arm": "T_Brick_ORM.png"}
    assert names_of(tile) == {"albedo": "T_Tile_BC.png", "normal": "T_Tile_N.png", "arm": "T_Tile_ORM.png"}
    assert brick.normal_convention == tile.normal_convention == "directx"
    assert brick.problems == tile.problems == []
    assert normal_convention_from_name("T_Brick_N_2K.tga") == "directx"


@pytest.mark.parametrize("arm", ["x_ORM.png", "x_occlusionRoughnessMetallic.png", "x_Occlusion_Roughness_Metallic.png"])
def test_gltf_orm_names_are_arm(tmp_path: Path, arm: str) -> None:
    make_folder(tmp_path, ["x_baseColor.png", "x_normal_gl.png", arm])
    (found,) = scan_assets(tmp_path).materials
    assert found.files["arm"] == arm and found.problems == []


def test_mra_and_inner_single_letters_match_no_role(tmp_path: Path) -> None:
    # MRA packs metallic, roughness, AO: another channel order than ARM, so it is not taken for one.
    # A single letter counts only as the last token after a material name: `T_D_Brick` and a bare `n` are not.
    odd = ("x_MRA.png", "T_D_Brick.png", "n_x.png", "n.png", "D.png")
    make_folder(tmp_path, ["x_col.png", "x_nor_gl.png", "x_rough.png", *odd])
    scan = scan_assets(tmp_path)
    (found,) = scan.materials
    assert names_of(found) == {"albedo": "x_col.png", "normal": "x_nor_gl.png", "roughness": "x_rough.png"}
    assert unplaced(scan) == {name: "name matches no role" for name in odd}


# --------------------------------------------------------------------------------------------- grouping


def test_prefixes_ignore_resolution_and_format_but_keep_numbers(tmp_path: Path) -> None:
    make_folder(tmp_path / "mixed", [
        "Metal009_2K_Color.jpg", "Metal009_2K_NormalDX.jpg", "Metal009_2K_Roughness.jpg",
        "Tiles088_1K-JPG_Color.jpg", "Tiles088_1K-JPG_NormalGL.jpg", "Tiles088_1K-JPG_Roughness.jpg",
        "brick_01_diff_2k.jpg", "brick_01_nor_gl_2k.jpg", "brick_01_arm_2k.jpg",
        "brick_02_diff_2k.jpg", "brick_02_nor_gl_2k.jpg", "brick_02_arm_2k.jpg",
    ])
    scan = scan_assets(tmp_path)
    assert list(by_output(scan)) == ["mixed/Metal009", "mixed/Tiles088", "mixed/brick_01", "mixed/brick_02"]
    assert [found.material for found in scan.materials] == [
        "mixed/Metal009", "mixed/Tiles088", "mixed/brick_01", "mixed/brick_02"]
    assert by_output(scan)["mixed/Metal009"].normal_convention == "directx"
    assert by_output(scan)["mixed/Tiles088"].normal_convention == "opengl"
    for found in scan.materials:
        assert found.problems == [] and len(found.files) == 3
        prefix = found.output.split("/")[1]
        assert all(Path(path).name.startswith(prefix + "_") for path in found.files.values())


def test_prefixes_compare_case_insensitively(tmp_path: Path) -> None:
    make_folder(tmp_path, ["Wood_BaseColor.png", "wood_normal_gl.png", "WOOD_ARM.png",
                           "Metal_BaseColor.png", "metal_Normal_OpenGL.png", "Metal_ORM.png"])
    scan = scan_assets(tmp_path)
    assert list(by_output(scan)) == ["Metal", "Wood"]  # the prefix as written in the albedo's name
    assert names_of(by_output(scan)["Wood"]) == {"albedo": "Wood_BaseColor.png", "normal": "wood_normal_gl.png",
                                                 "arm": "WOOD_ARM.png"}


def test_groups_without_an_albedo_are_unplaced_in_a_shared_folder(tmp_path: Path) -> None:
    make_folder(tmp_path / "export", ["Wood_BaseColor.png", "Wood_Normal_OpenGL.png", "Wood_ORM.png",
                                      "Metal_BaseColor.png", "Metal_Normal_OpenGL.png", "Metal_ORM.png",
                                      "Stone_Normal_OpenGL.png", "Stone_Height.png", "Wood_Height.png"])
    scan = scan_assets(tmp_path)
    assert sorted(by_output(scan)) == ["export/Metal", "export/Wood"]
    assert by_output(scan)["export/Wood"].files["height"] == "export/Wood_Height.png"
    assert "height" not in by_output(scan)["export/Metal"].files
    assert unplaced(scan) == {
        "export/Stone_Height.png": "no albedo with the prefix 'Stone' in this folder",
        "export/Stone_Normal_OpenGL.png": "no albedo with the prefix 'Stone' in this folder",
    }


def test_unprefixed_set_next_to_prefixed_ones_is_the_folders_own(tmp_path: Path) -> None:
    make_folder(tmp_path / "m", ["albedo.png", "normal_gl.png", "arm.png",
                                 "Wood_BaseColor.png", "Wood_Normal_OpenGL.png", "Wood_ORM.png"])
    scan = scan_assets(tmp_path)
    assert {found.output: found.material for found in scan.materials} == {"m": "m", "m/Wood": "m/Wood"}
    assert names_of(by_output(scan)["m"]) == {"albedo": "albedo.png", "normal": "normal_gl.png", "arm": "arm.png"}


def test_one_albedo_makes_the_folder_one_material_as_compress_does(tmp_path: Path) -> None:
    # Different prefixes, but only one has an albedo: the folder is one material, as `bcf compress` sees it.
    make_folder(tmp_path / "set", ["rock_col.png", "rock_nor_gl.png", "other_rough.png", "Rock_height.png"])
    scan = scan_assets(tmp_path)
    (found,) = scan.materials
    assert found.output == "set" and found.material == "set" and found.problems == []
    assert names_of(found) == {"albedo": "rock_col.png", "normal": "rock_nor_gl.png",
                               "roughness": "other_rough.png", "height": "Rock_height.png"}


def test_shared_output_folder_is_a_problem(tmp_path: Path) -> None:
    make_folder(tmp_path / "lib", ["Wood_BaseColor.png", "Wood_Normal_OpenGL.png", "Wood_ORM.png",
                                   "Metal_BaseColor.png", "Metal_Normal_OpenGL.png", "Metal_ORM.png"])
    make_folder(tmp_path / "lib" / "wood", ["albedo.png", "normal_gl.png", "arm.png"])
    scan = scan_assets(tmp_path)
    assert by_output(scan)["lib/Metal"].problems == []
    for output in ("lib/Wood", "lib/wood"):
        (problem,) = by_output(scan)[output].problems
        assert "output folder" in problem and output in problem


# ------------------------------------------------------------------------------------ tree and problems


def test_nested_tree_with_a_material_at_the_root(tmp_path: Path) -> None:
    root = tmp_path / "assets"
    make_folder(root, ["albedo.png", "normal_gl.png", "arm.png", "LICENSE", "readme.txt"])
    make_folder(root / "wood", ["planks_diff_1k.jpg", "planks_nor_gl_1k.jpg", "planks_arm_1k.jpg"])
    make_folder(root / "wood" / "oak" / "aged", ["oak_diff.png", "oak_nor_dx.png", "oak_rough.png", "oak.blend"])
    make_folder(root / "empty" / "only_text", ["notes.txt", "scene.json"])
    scan = scan_assets(root)
    assert [(found.material, found.dir, found.output) for found in scan.materials] == [
        ("assets", ".", "."),
        ("wood", "wood", "wood"),
        ("aged", "wood/oak/aged", "wood/oak/aged"),
    ]
    assert by_output(scan)["."].files == {"albedo": "albedo.png", "normal": "normal_gl.png", "arm": "arm.png"}
    assert by_output(scan)["wood/oak/aged"].files == {"albedo": "wood/oak/aged/oak_diff.png",
                                                      "normal": "wood/oak/aged/oak_nor_dx.png",
                                                      "roughness": "wood/oak/aged/oak_rough.png"}
    assert by_output(scan)["wood/oak/aged"].normal_convention == "directx"
    assert all(found.problems == [] for found in scan.materials)
    assert scan.unplaced == []  # non-image files are skipped silently


def test_hidden_files_and_archive_clutter_are_skipped(tmp_path: Path) -> None:
    make_folder(tmp_path / "rock", ["rock_col.png", "rock_nor_gl.png", "rock_arm.png", "._rock_col.png",
                                    ".thumb.png"])
    make_folder(tmp_path / "__MACOSX" / "rock", ["._rock_col.png", "rock_col.png"])
    make_folder(tmp_path / ".git" / "x", ["albedo.png", "normal_gl.png", "rough.png"])
    scan = scan_assets(tmp_path)
    assert [found.output for found in scan.materials] == ["rock"]
    assert by_output(scan)["rock"].problems == [] and scan.unplaced == []


def test_incomplete_set_unknown_image_and_non_image(tmp_path: Path) -> None:
    make_folder(tmp_path / "rock", ["rock_col.png", "rock_rough.png", "rock_photo.png", "LICENSE.txt", "rock.blend"])
    make_folder(tmp_path / "heights", ["cliff_height.png"])
    scan = scan_assets(tmp_path)
    (found,) = scan.materials
    assert found.output == "rock" and names_of(found) == {"albedo": "rock_col.png", "roughness": "rock_rough.png"}
    assert len(found.problems) == 1 and "normal" in found.problems[0] and "missing" in found.problems[0]
    assert found.resolution == (8, 8)
    assert unplaced(scan) == {"rock/rock_photo.png": "name matches no role",
                              "heights/cliff_height.png": "no albedo, normal or roughness map in this folder"}
    # The scan also passes on discovery's note about the unknown image, as `bcf compress rock` would show it.
    assert any("rock_photo.png" in note for note in found.notes)


def test_missing_albedo_and_roughness(tmp_path: Path) -> None:
    make_folder(tmp_path, ["x_nor_gl.png", "x_ao.png"])
    (found,) = scan_assets(tmp_path).materials
    assert found.resolution is None
    assert found.problems == ["incomplete material: missing albedo, roughness (or an ARM map)"]


def test_two_candidates_for_a_role_is_a_problem_not_an_exception(tmp_path: Path) -> None:
    make_folder(tmp_path / "x", ["x_diff_1k.png", "x_diff_2k.png", "x_nor_gl.png", "x_rough.png"])
    with pytest.raises(MaterialError):
        discover_material(tmp_path / "x")
    (found,) = scan_assets(tmp_path).materials
    (problem,) = found.problems  # ambiguous, not reported as missing too
    assert "x_diff_1k.png" in problem and "x_diff_2k.png" in problem and "albedo" in problem
    assert "albedo" not in found.files and found.resolution is None
    assert names_of(found) == {"normal": "x_nor_gl.png", "roughness": "x_rough.png"}


def test_discovery_notes_are_kept(tmp_path: Path) -> None:
    make_folder(tmp_path, ["x_diff.png", "x_nor_gl.png", "x_nor_dx.png", "x_arm.png", "x_rough.png"])
    (found,) = scan_assets(tmp_path).materials
    assert found.files["normal"] == "x_nor_gl.png" and found.normal_convention == "opengl"
    assert any("both OpenGL and DirectX" in note for note in found.notes)
    assert any("using the ARM map x_arm.png" in note for note in found.notes)
    assert found.notes == discover_material(tmp_path).notes


def test_complete_material_loads(tmp_path: Path) -> None:
    make_folder(tmp_path / "lib" / "rock", ["rock_diff.png", "rock_nor_gl.png", "rock_arm.png"], size=(64, 64))
    root = tmp_path / "lib"
    (found,) = scan_assets(root).materials
    texture_set = load_texture_set(found.material_files(root), name=found.material)
    assert texture_set.channels.shape == (64, 64, 8)
    assert texture_set.source.name == "rock" and texture_set.source.arm_packed
    assert texture_set.source.normal_convention == "opengl"
    assert found.resolution == (64, 64)


def test_root_must_be_a_folder(tmp_path: Path) -> None:
    with pytest.raises(MaterialError, match="no such folder"):
        scan_assets(tmp_path / "missing")
    write_image(tmp_path / "x.png")
    with pytest.raises(MaterialError, match="not a folder"):
        scan_assets(tmp_path / "x.png")


def test_scanning_twice_gives_equal_results(tmp_path: Path) -> None:
    make_folder(tmp_path / "b", ["Wood_BaseColor.png", "Wood_Normal_OpenGL.png", "Wood_ORM.png",
                                 "Metal_BaseColor.png", "Metal_Normal.png", "Stone_Height.png", "z.png"])
    make_folder(tmp_path / "a" / "c", ["rock_col.png", "rock_nor_gl.png", "rock_rough.png"])
    first, second = scan_assets(tmp_path), scan_assets(tmp_path)
    assert first == second
    assert first.model_dump_json() == second.model_dump_json()
    assert [found.output for found in first.materials] == sorted(found.output for found in first.materials)
    assert [entry.path for entry in first.unplaced] == sorted(entry.path for entry in first.unplaced)
