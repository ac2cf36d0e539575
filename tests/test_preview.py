"""`bcf preview`: a real (briefly fitted) export of examples/sample rendered on a sphere by Mesa's OpenGL (llvmpipe
through EGL), next to the original textures rendered by the same shading code.

GL is required, never skipped: without it the tests fail and say why.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from bcf.engine import gl
from bcf.engine import preview
from bcf_command import run_bcf

pytestmark = pytest.mark.gl

SAMPLE = Path(__file__).resolve().parent.parent / "examples" / "sample"
SIZE = 128
# Decoded vs original sphere, PSNR over the sphere's pixels (background excluded, it is identical in both). The
# 60 + 60 iteration fit scores 26.9 dB aggregate in report.json and its sphere renders 24.7 dB from the original
# (llvmpipe, size 128, default light). 23 dB leaves 1.7 dB for other CPUs and drivers while still failing
# the mistakes we tried: the original with albedo upside down (21.4 dB) or as BGR (20.8 dB), shifted by 8 pixels
# (21.6 dB), albedo decoded as linear (16.7 dB), a flat sphere of the mean colour (16.7 dB).
MIN_SPHERE_PSNR_DB = 23.0


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """examples/sample compressed for a few seconds (lossy on purpose: the panels must differ)."""
    out = tmp_path_factory.mktemp("preview") / "out"
    done = run_bcf("compress", SAMPLE, "-o", out, "--preset", "fast", "--phase1-iterations", "60",
                   "--phase2-iterations", "60", "--batch-size", "4096", "-q")
    assert done.returncode == 0, done.stderr
    return out


@pytest.fixture(scope="module")
def images(exported: Path) -> preview.PreviewImages:
    try:
        return preview.render_preview(exported, SAMPLE, size=SIZE)
    except gl.GLUnavailable as exc:  # fail, never skip: CI must have Mesa (installed by .ci/run)
        pytest.fail(f"headless OpenGL is required: {exc}", pytrace=False)


def sphere_mask(size: int, inset: float = 0.97) -> np.ndarray:
    """Pixels whose centre lies well inside the sphere's silhouette (the edge pixels are partly background)."""
    centre = (np.arange(size) + 0.5) / size * 2 - 1
    return np.hypot(*np.meshgrid(centre, centre)) < preview.RADIUS * inset


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(1.0 / max(float(np.mean((a.astype(np.float64) - b) ** 2)), 1e-30))


def test_cli_writes_two_upright_panels(exported: Path, tmp_path: Path, images: preview.PreviewImages) -> None:
    output = tmp_path / "p.png"
    done = run_bcf("preview", exported, "-o", output, "--source", SAMPLE, "--size", SIZE)
    assert done.returncode == 0, done.stderr
    assert f"wrote {output}" in done.stdout
    assert "note:" not in done.stdout  # the source is the material that was compressed
    png = matplotlib.image.imread(output)[..., :3]
    (width, height), boxes = preview.panel_boxes(SIZE, 2)
    assert png.shape == (height, width, 3)
    panels = [png[top:top + SIZE, left:left + SIZE] for left, top in boxes]
    # Each panel is the rendered image, pixel for pixel (8-bit), in the order decoded, original.
    for panel, rendered in zip(panels, (images.decoded, images.original)):
        assert rendered is not None
        assert np.abs(panel - rendered).max() <= 1.5 / 255
        assert panel.std() > 0.05  # a textured, lit sphere, not one colour
    assert not np.array_equal(panels[0], panels[1])
    # The figure around the panels is darker than their background, and the titles are drawn above them.
    assert np.all(png[2, 2] < preview.BACKGROUND[0] - 0.05)
    title_rows = png[boxes[0][1] - 24:boxes[0][1] - 4, boxes[0][0]:boxes[0][0] + SIZE]
    assert title_rows.max() > 0.5


def test_decoded_and_original_spheres_are_similar_but_not_identical(images: preview.PreviewImages) -> None:
    assert images.original is not None
    for image in (images.decoded, images.original):
        assert image.shape == (SIZE, SIZE, 3) and image.dtype == np.float32
        assert 0.0 <= image.min() and image.max() <= 1.0
    mask = sphere_mask(SIZE)
    score = psnr(images.decoded[mask], images.original[mask])
    assert score > MIN_SPHERE_PSNR_DB, score
    assert np.abs(images.decoded - images.original).max() > 0.05  # the fast fit is lossy: not the same image
    assert images.material == "sample" and images.psnr_all is not None
    assert images.compressed_bytes > 0 and images.notes == ()


def test_sphere_is_lit_from_the_light_and_sits_on_the_background(exported: Path,
                                                                 images: preview.PreviewImages) -> None:
    """The default light comes from the upper left: that quadrant of the sphere is much brighter than the lower
    right (in shadow: ambient only). Everything outside the silhouette is exactly the background colour."""
    half = SIZE // 2
    inside = sphere_mask(SIZE)
    rows, cols = np.mgrid[:SIZE, :SIZE]
    outside = ~sphere_mask(SIZE, inset=1.05)
    for image in (images.decoded, images.original):
        assert image is not None
        lit = image[inside & (rows < half) & (cols < half)].mean()
        shadow = image[inside & (rows >= half) & (cols >= half)].mean()
        assert lit > 2 * shadow, (lit, shadow)
        np.testing.assert_allclose(image[outside], np.broadcast_to(preview.BACKGROUND, image[outside].shape),
                                   atol=1e-4)
    # Lit from the lower right instead, the quadrants swap: the light direction reaches the shader.
    moved = preview.render_preview(exported, size=64, light=(135.0, -35.0))
    assert moved.original is None
    inside, (rows, cols) = sphere_mask(64), np.mgrid[:64, :64]
    lit = moved.decoded[inside & (rows >= 32) & (cols >= 32)].mean()
    shadow = moved.decoded[inside & (rows < 32) & (cols < 32)].mean()
    assert lit > 2 * shadow, (lit, shadow)


def test_a_changed_source_gives_a_note_not_an_error(exported: Path, tmp_path: Path) -> None:
    source = tmp_path / "sample"
    shutil.copytree(SAMPLE, source)
    albedo = source / "albedo.png"
    image = matplotlib.image.imread(albedo)
    matplotlib.image.imsave(albedo, np.clip(image * 0.9, 0, 1))
    result = preview.render_preview(exported, source, size=32)
    assert result.original is not None
    assert any("albedo" in note and "differs" in note for note in result.notes), result.notes


def test_bad_folder_is_a_user_error(tmp_path: Path) -> None:
    done = run_bcf("preview", tmp_path, "-o", tmp_path / "p.png")
    assert done.returncode == 2
    assert done.stderr.startswith("bcf: error:") and "manifest.json" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "p.png").exists()


def test_normal_maps_tilt_the_shading_the_way_their_convention_says() -> None:
    """A dome in the middle of a flat grey material (normal map from its height, OpenGL convention) faces the
    light on its upper half when lit from above and on its left half when lit from the left; read as DirectX
    (y flipped) the upper and lower halves swap. Compared with the same sphere without the dome."""
    size = 128
    rows, cols = np.mgrid[:size, :size]
    height = np.sqrt(np.clip(1 - ((cols - size / 2) ** 2 + (rows - size / 2) ** 2) / (size / 4) ** 2, 0, 1)) * size / 8
    dh_drow, dh_dcol = np.gradient(height)
    normal = np.stack([-dh_dcol, dh_drow, np.ones_like(height)], -1)  # OpenGL: +y towards the image's top row
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    flat = np.zeros((size, size, 8), np.float32)
    flat[..., 0:5] = 0.5
    flat[..., 5:7] = (1.0, 0.8)
    dome = flat.copy()
    dome[..., 3:5] = (normal[..., :2] + 1) / 2
    # The tile's centre faces the camera on the equator, which the sphere's tilt moves below the panel's centre.
    centre = 64 + round(math.sin(math.radians(preview.TILT_DEGREES)) * preview.RADIUS * 64)
    try:
        context = gl.HeadlessGL()
    except gl.GLUnavailable as exc:
        pytest.fail(f"headless OpenGL is required: {exc}", pytrace=False)

    def render(channels: np.ndarray, light: tuple[float, float], convention: str) -> np.ndarray:
        textures = {name: context.float_texture(channels[..., part]) for name, part in
                    (("src_albedo", slice(0, 3)), ("src_normal", slice(3, 5)), ("src_arm", slice(5, 8)))}
        image = preview._render_sphere(context, preview._SOURCE_LOOKUP, textures, 128, light, convention, "wrap")
        return image.mean(-1)[centre - 20:centre + 20, 44:84]

    with context:
        for light, convention, top_minus_bottom, left_minus_right in (
                ((0.0, 60.0), "opengl", 1, 0), ((-60.0, 10.0), "opengl", 0, 1), ((0.0, 60.0), "directx", -1, 0)):
            bump = render(dome, light, convention) - render(flat, light, convention)
            vertical = float(bump[:20].mean() - bump[20:].mean())
            horizontal = float(bump[:, :20].mean() - bump[:, 20:].mean())
            for got, sign in ((vertical, top_minus_bottom), (horizontal, left_minus_right)):
                if sign:
                    assert got * sign > 0.02, (light, convention, vertical, horizontal)
