"""The generated decoders in a real renderer we did not write: Mesa's OpenGL (llvmpipe, through EGL) samples the
exported BC6H files with its own texture units, and the GLSL `bcf shader` writes (and the HLSL, compiled by
glslang to SPIR-V and cross-compiled by SPIRV-Cross) must reproduce the reference decoder at the same (u, v, s)."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
import torch

from bcf.core import load_export
from bcf.core.codec import bc6h
from bcf.core import pipeline as compress
from bcf.core.codec import containers
from bcf.core.export import artifacts as export
from bcf.core.report import metrics
from bcf.engine.gl import GLUnavailable, HeadlessGL
from bcf.core.material.texture_set import load_material
from bcf.core.options import CompressOptions
from bcf.engine.shader import shader_source
from bcf_command import run_bcf

pytestmark = pytest.mark.gl

CHAINMAIL = Path(__file__).parent / "data" / "chainmail_128"
MIN_PSNR_DB = 45.0
OUTPUTS = """layout(location = 0) out vec4 o_albedo;
layout(location = 1) out vec4 o_normal;
layout(location = 2) out vec4 o_arm;
uniform vec2 u_size;
uniform float u_s;
uniform int u_mode;
"""
MAIN = """
void main() {
    vec2 uv = gl_FragCoord.xy / u_size;  // texel centres of a u_size grid: row 0 of the result is v = 0.5 / h
    BcfMaterial m;
    if (u_mode == 0) m = bcf_decode(uv);                            // hardware LOD from derivatives
    else if (u_mode == 1) m = bcf_decode_lod(uv, u_s);              // explicit material scale
    else m = bcf_decode_grad(uv, dFdx(uv), dFdy(uv));               // explicit derivatives
    o_albedo = vec4(m.albedo_srgb, 1.0);
    o_normal = vec4(m.normal.xy * 0.5 + 0.5, m.normal.z, 1.0);
    o_arm = vec4(m.arm, 1.0);
}
"""


@pytest.fixture(scope="module")
def gl() -> Iterator[HeadlessGL]:
    try:
        context = HeadlessGL()
    except GLUnavailable as exc:  # fail, never skip: CI must have Mesa (installed by .ci/run)
        pytest.fail(f"headless OpenGL is required: {exc}", pytrace=False)
    assert "llvmpipe" in context.renderer, context.renderer
    yield context
    context.close()


@pytest.fixture(scope="module", params=["wrap", "clamp"])
def exported(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> export.ExportedMaterial:
    """The real 128x128 Chainmail004 crop, fitted briefly, in both address modes."""
    torch.set_num_threads(1)
    folder = tmp_path_factory.mktemp(f"export-{request.param}") / "out"
    options = CompressOptions(preset="fast", phase1_iterations=150, phase2_iterations=150, batch_size=4096,
                              address=request.param)
    compress.compress_material(load_material(CHAINMAIL), options, folder)
    return load_export(folder)


def feature_textures(gl: HeadlessGL, exported: export.ExportedMaterial) -> list[Any]:
    m = exported.manifest
    return [gl.bc6h_texture(containers.read_dds(exported.directory / t.file), m.address) for t in m.feature_textures]


def reference(exported: export.ExportedMaterial, size: tuple[int, int], s: float) -> np.ndarray:
    """The reference decoder at the texel centres of a w x h grid and scale s, saturated: (h, w, 8)."""
    return metrics.render_mip(exported.model, size[0], size[1], s).clamp(0, 1).permute(1, 2, 0).numpy()


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(1.0 / max(float(np.mean((a.astype(np.float64) - b) ** 2)), 1e-30))


def scores(rendered: list[np.ndarray], expected: np.ndarray) -> dict[str, float]:
    albedo, normal, arm = rendered
    return {"albedo": psnr(albedo[..., :3], expected[..., 0:3]), "normal": psnr(normal[..., :2], expected[..., 3:5]),
            "arm": psnr(arm[..., :3], expected[..., 5:8])}


# (viewport, mode, explicit s): mip 0..2 through the hardware LOD, a minified view at a fractional LOD
# (128 -> 48 texels: s = 1.415), explicit fractional scales, and explicit derivatives.
CASES = [((128, 128), 0, 0.0), ((64, 64), 0, 1.0), ((32, 32), 0, 2.0), ((48, 48), 0, math.log2(128 / 48)),
         ((128, 128), 1, 1.25), ((64, 64), 1, 2.6), ((96, 96), 1, 0.4), ((40, 40), 2, math.log2(128 / 40))]


def test_glsl_decoder_matches_the_reference_at_every_scale(gl: HeadlessGL, exported: export.ExportedMaterial) -> None:
    source = "#version 330 core\n" + OUTPUTS + shader_source(exported.directory, "glsl") + MAIN
    textures = feature_textures(gl, exported)
    for size, mode, s in CASES:
        rendered = gl.render_bc6h_material(source, size, textures, {"u_size": size, "u_s": s, "u_mode": mode}, 3)
        got = scores(rendered, reference(exported, size, s))
        assert min(got.values()) >= MIN_PSNR_DB, (size, mode, s, got)
        # The rebuilt z is what the format says: sqrt(1 - x^2 - y^2) of the decoded x, y.
        n = rendered[1][..., :2] * 2 - 1
        np.testing.assert_allclose(rendered[1][..., 2], np.sqrt(np.clip(1 - (n ** 2).sum(-1), 0, 1)), atol=1e-5)


def test_gl_returns_our_bc6h_texels_exactly(gl: HeadlessGL, exported: export.ExportedMaterial) -> None:
    """Every level of every feature texture, read with textureLod at its exact texel centres, is bit for bit
    what bcf's BC6H decoder gives (and what the training saw)."""
    m = exported.manifest
    for entry, texture in zip(m.feature_textures, feature_textures(gl, exported)):
        dds = containers.read_dds(exported.directory / entry.file)
        for level in range(entry.mips):
            w, h = dds.level_size(level)
            ours = bc6h.decode_image(dds.levels[level], w, h, signed=False).astype(np.float32)
            fragment = ("#version 330 core\nuniform sampler2D t;\nuniform vec2 u_size;\nuniform float u_level;\n"
                        "out vec4 o;\nvoid main() { o = textureLod(t, gl_FragCoord.xy / u_size, u_level); }\n")
            sampled = gl.render(fragment, (w, h), {"t": texture}, {"u_size": (w, h), "u_level": float(level)})[0]
            assert np.array_equal(sampled[..., :3], ours), (entry.file, level)
            stored = gl.read_texture_level(texture, level, (w, h))
            assert np.array_equal(stored.view(np.uint16), ours.astype(np.float16).view(np.uint16))


def _hlsl_as_glsl(hlsl: str, folder: Path) -> str:
    """HLSL -> SPIR-V (glslang, the Khronos reference front end) -> GLSL 3.30 (SPIRV-Cross)."""
    for tool in ("glslangValidator", "spirv-cross"):
        assert shutil.which(tool), f"{tool} is required (Debian glslang-tools, spirv-cross; .ci/run installs them)"
    source, spirv, glsl = folder / "decoder.hlsl", folder / "decoder.spv", folder / "decoder.frag"
    source.write_text(hlsl)
    compiled = subprocess.run(["glslangValidator", "-D", "-V", "-S", "frag", "-e", "main", "-o", spirv, source],
                              capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stdout + compiled.stderr
    crossed = subprocess.run(["spirv-cross", spirv, "--version", "330", "--no-es", "--output", glsl],
                             capture_output=True, text=True)
    assert crossed.returncode == 0, crossed.stderr
    return glsl.read_text()


HLSL_MAIN = """
cbuffer Params : register(b0) { float2 u_size; float u_s; int u_mode; };
struct Out { float4 albedo : SV_Target0; float4 normal : SV_Target1; float4 arm : SV_Target2; };
Out main(float4 position : SV_Position) {
    float2 uv = position.xy / u_size;
    BcfMaterial m;
    if (u_mode == 0) m = bcf_decode(uv);
    else if (u_mode == 1) m = bcf_decode_lod(uv, u_s);
    else m = bcf_decode_grad(uv, ddx(uv), ddy(uv));
    Out o;
    o.albedo = float4(m.albedo_srgb, 1.0);
    o.normal = float4(m.normal.xy * 0.5 + 0.5, m.normal.z, 1.0);
    o.arm = float4(m.arm, 1.0);
    return o;
}
"""


def test_hlsl_decoder_compiled_by_glslang_matches_the_reference(gl: HeadlessGL, exported: export.ExportedMaterial,
                                                                tmp_path: Path) -> None:
    glsl = _hlsl_as_glsl(shader_source(exported.directory, "hlsl") + HLSL_MAIN, tmp_path)
    # SPIRV-Cross combines each texture with the sampler and turns the cbuffer into a uniform block.
    samplers = re.findall(r"uniform sampler2D (\w+);", glsl)
    assert len(samplers) == 4
    textures = dict(zip(sorted(samplers, key=lambda name: re.search(r"bcf_T(\d)", name).group(1)),
                        feature_textures(gl, exported)))
    block = re.search(r"(?:layout\([^)]*\)\s*)?uniform (?:type_)?Params\s*\{([^}]*)\}\s*(\w+);", glsl)
    assert block, glsl[:2000]
    plain = "\n".join(f"uniform {line.strip()}" for line in block.group(1).splitlines() if line.strip())
    glsl = glsl.replace(block.group(0), plain).replace(f"{block.group(2)}.", "")  # plain uniforms, same names
    for size, mode, s in CASES[:1] + CASES[3:5] + CASES[-1:]:
        uniforms = {"u_size": size, "u_s": s, "u_mode": mode}
        rendered = gl.render(glsl, size, textures, uniforms, 3)
        got = scores(rendered, reference(exported, size, s))
        assert min(got.values()) >= MIN_PSNR_DB, (size, mode, s, got)


def test_the_shader_command_writes_what_the_library_generates(exported: export.ExportedMaterial,
                                                              tmp_path: Path) -> None:
    for language in ("glsl", "hlsl"):
        target = tmp_path / f"decoder.{language}"
        result = run_bcf("shader", exported.directory, "--lang", language, "-o", target)
        assert result.returncode == 0, result.stderr
        assert target.read_text() == shader_source(exported.directory, language)
        text = target.read_text()
        assert f'"{exported.manifest.material.name}"' in text and "bcf_decode_lod" in text
    printed = run_bcf("shader", exported.directory, "--lang", "glsl")
    assert printed.returncode == 0 and printed.stdout == shader_source(exported.directory, "glsl")
    missing = run_bcf("shader", tmp_path / "nope", "--lang", "glsl")
    assert missing.returncode == 2 and missing.stderr.startswith("bcf: error:")
