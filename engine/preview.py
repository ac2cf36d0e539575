"""`bcf preview`: the compressed material on a lit sphere, rendered by a real OpenGL driver, optionally next to
the original textures rendered the same way.

The decoded sphere samples the four BC6H feature textures through the GPU path (the GLSL of `bcf shader`,
`bcf_decode_grad`), so the preview shows what an engine would show, block compression and trilinear filtering
included. The original sphere swaps only the material lookup: a GLSL function with the same name and signature
that samples the source channels uploaded as mipmapped float textures. Everything else (the sphere, its uv
derivatives, tangent frame, lighting, tone mapping) is one shared source, so the two panels differ only where
the material differs.

Rendering runs headless through `bcf.core.gl` (EGL, Mesa's llvmpipe without a GPU); composing the figure uses
matplotlib's Agg backend. Images are returned upright (row 0 = top), sRGB-encoded, in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional, Sequence

import numpy as np

from bcf.core import TEXTURES, MaterialSource, atomic_path, load_material, read_dds
from bcf.engine import gl

if TYPE_CHECKING:
    from bcf.core import Manifest

# Reading an export imports torch (about 1.5 s): it is imported where a preview is rendered, so the CLI can read
# this module's defaults for `bcf --help` without loading torch.

__all__ = ["BACKGROUND", "DEFAULT_LIGHT", "MAX_SIZE", "MIN_SIZE", "PreviewImages", "panel_boxes", "panel_titles",
           "render_preview", "source_mismatches", "write_preview"]

# Light from the upper left, a little in front of the sphere: the classic key-light position, so the lit side,
# the terminator and the rim in shadow are all visible. (azimuth, elevation) in degrees; see `_light_direction`.
DEFAULT_LIGHT = (-45.0, 35.0)
# Neutral dark grey behind the sphere (sRGB-encoded, as written to the image), dark enough that bright
# specular highlights and pale albedos stand out, light enough to tell from the black of a shadowed rim.
BACKGROUND = (0.2, 0.2, 0.2)
MIN_SIZE = 32
MAX_SIZE = 2048
# Each panel pixel is the mean of SUPERSAMPLE x SUPERSAMPLE shaded samples: anti-aliases the silhouette and
# specular aliasing from normal-map detail; the texture LOD then follows the finer sampling grid, as with MSAA
# plus sample shading in an engine.
SUPERSAMPLE = 2
# The sphere is tilted towards the camera by this angle, so the north pole (where longitude/latitude uv
# pinches) is in view instead of hidden on the silhouette.
TILT_DEGREES = 20.0
# Material repeats around the sphere (u) and from pole to pole (v): with 2 x 1 a tile covers the same arc length
# in both directions (half the circumference = the meridian), so texels stay square at the equator.
TILING = (2.0, 1.0)
# Sphere radius as a fraction of half the panel: a margin of background around it.
RADIUS = 0.9

# The material lookup for the original textures: the same name, signature and struct as the generated decoder's
# `bcf_decode_grad`, so the shading source below works unchanged with either. Values are as stored, like the
# decoder's outputs: albedo sRGB-encoded, normal x, y as (n + 1) / 2 with z rebuilt the same way.
_SOURCE_LOOKUP = """uniform sampler2D src_albedo;
uniform sampler2D src_normal;
uniform sampler2D src_arm;

struct BcfMaterial {
    vec3 albedo_srgb;
    vec3 normal;
    vec3 arm;
};

BcfMaterial bcf_decode_grad(vec2 uv, vec2 dx, vec2 dy) {
    BcfMaterial m;
    m.albedo_srgb = clamp(textureGrad(src_albedo, uv, dx, dy).rgb, 0.0, 1.0);
    vec2 n = clamp(textureGrad(src_normal, uv, dx, dy).rg, 0.0, 1.0) * 2.0 - 1.0;
    m.normal = vec3(n, sqrt(clamp(1.0 - dot(n, n), 0.0, 1.0)));
    m.arm = clamp(textureGrad(src_arm, uv, dx, dy).rgb, 0.0, 1.0);
    return m;
}
"""

# The sphere and its shading, appended to either material lookup. Output: tone-mapped LINEAR colour composited
# over the (linear) background; sRGB encoding happens after the supersampling box filter, so that filter
# averages light, not encoded values.
_SHADING = """
out vec4 o_colour;
uniform vec2 u_size;          // viewport in pixels (square)
uniform vec3 u_light;         // unit direction towards the light, view space (x right, y up, z to the camera)
uniform vec2 u_tiling;        // material repeats in u, v
uniform float u_normal_y;     // +1 OpenGL (Y+) normal maps, -1 DirectX (Y-): flips the tangent-space y
uniform float u_tilt;         // radians the sphere is tilted towards the camera
uniform float u_radius;       // sphere radius in half-viewport units
uniform vec3 u_background;    // linear

const float PI = 3.14159265358979;
const vec3 LIGHT_COLOUR = vec3(4.0);   // a bright key light: albedo 1 facing it reaches the tone map's shoulder
const vec3 AMBIENT = vec3(0.08);       // dim fill so the shadow side keeps some texture, scaled by AO

vec3 srgb_to_linear(vec3 c) {
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), c));
}

// Narkowicz's ACES filmic fit: a gentle shoulder so highlights roll off instead of clipping.
vec3 tone_map(vec3 x) {
    return clamp((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0);
}

// Object space from view space: rotate about x so the camera looks down on the sphere by u_tilt.
vec3 to_object(vec3 v) {
    float c = cos(u_tilt), s = sin(u_tilt);
    return vec3(v.x, c * v.y + s * v.z, -s * v.y + c * v.z);
}

// The derivative of uv with the smaller magnitude per component, between uv itself and a copy whose wrap point
// is moved by half a tile: atan's jump at the back of the sphere (and the tiling's integer jumps) shows up in
// only one of the two, so the lookup does not pick the coarsest mip along that seam.
vec2 seamless(vec2 d_plain, vec2 d_shifted) {
    return vec2(abs(d_plain.x) <= abs(d_shifted.x) ? d_plain.x : d_shifted.x,
                abs(d_plain.y) <= abs(d_shifted.y) ? d_plain.y : d_shifted.y);
}

void main() {
    // Orthographic camera: each pixel is a ray along -z; p is the ray's position in sphere radii.
    vec2 p = (gl_FragCoord.xy / u_size * 2.0 - 1.0) / u_radius;
    float r = length(p);
    float pixel = 2.0 / (u_size.x * u_radius);   // one pixel in sphere radii
    // Keep every pixel's uv finite (rays that miss are pulled onto the silhouette) and compute derivatives in
    // uniform control flow: dFdx/dFdy across a 2x2 quad that straddles the silhouette must stay meaningful.
    vec2 q = r > 0.9999 ? p / r * 0.9999 : p;
    vec3 n_view = vec3(q, sqrt(max(1.0 - dot(q, q), 0.0)));
    vec3 n = to_object(n_view);

    // Longitude / latitude mapping; v runs from the north pole (0) to the south pole (1) so the image's top row
    // (t = 0) is at the top and the texture appears upright and unmirrored from the front. u is offset so the
    // middle of a tile faces the camera: tile edges fall on the silhouette, where a material that does not tile
    // seamlessly shows its edge least.
    float longitude = atan(n.x, n.z);
    float latitude = asin(clamp(n.y, -1.0, 1.0));
    vec2 uv = vec2(longitude / (2.0 * PI) + 0.25, 0.5 - latitude / PI) * u_tiling;
    vec2 shifted = fract(uv + 0.5) - 0.5;
    vec2 dx = seamless(dFdx(uv), dFdx(shifted));
    vec2 dy = seamless(dFdy(uv), dFdy(shifted));
    BcfMaterial m = bcf_decode_grad(uv, dx, dy);

    // Tangent frame of the mapping: T towards +u (east, +longitude), B towards the image's up (north, the
    // direction an OpenGL normal map's +y points), N outward. Right-handed: T x B = N.
    vec3 T = normalize(vec3(cos(longitude), 0.0, -sin(longitude)));
    vec3 B = cross(n, T);
    vec3 ts = vec3(m.normal.x, m.normal.y * u_normal_y, m.normal.z);
    vec3 N = normalize(T * ts.x + B * ts.y + n * max(ts.z, 1e-4));

    vec3 L = to_object(u_light);
    vec3 V = to_object(vec3(0.0, 0.0, 1.0));
    vec3 H = normalize(L + V);
    vec3 albedo = srgb_to_linear(m.albedo_srgb);
    float ao = m.arm.x;
    float roughness = max(m.arm.y, 0.04);   // GGX with alpha -> 0 is a delta: keep highlights renderable
    float metalness = m.arm.z;

    float NoL = max(dot(N, L), 0.0);
    float NoV = max(dot(N, V), 1e-4);
    float NoH = max(dot(N, H), 0.0);
    float VoH = max(dot(V, H), 0.0);
    // Normal maps can tilt N towards a light that is behind the geometric surface; fade direct light out
    // across the geometric terminator instead.
    float horizon = smoothstep(-0.02, 0.1, dot(n, L));

    // Metalness workflow: dielectrics reflect 4 % at normal incidence; metals tint the reflection by albedo
    // and have no diffuse term.
    vec3 F0 = mix(vec3(0.04), albedo, metalness);
    float a = roughness * roughness;
    float a2 = a * a;
    float d = NoH * NoH * (a2 - 1.0) + 1.0;
    float D = a2 / (PI * d * d);                                       // GGX / Trowbridge-Reitz
    float k = (roughness + 1.0) * (roughness + 1.0) / 8.0;             // Smith-Schlick, k for analytic lights
    float G = (NoL / (NoL * (1.0 - k) + k)) * (NoV / (NoV * (1.0 - k) + k));
    vec3 F = F0 + (1.0 - F0) * pow(1.0 - VoH, 5.0);                    // Schlick
    vec3 specular = D * G * F / max(4.0 * NoL * NoV, 1e-4);
    vec3 diffuse = (1.0 - F) * (1.0 - metalness) * albedo / PI;       // Lambert
    vec3 direct = (diffuse + specular) * LIGHT_COLOUR * NoL * horizon;
    vec3 ambient = AMBIENT * ((1.0 - metalness) * albedo + F0) * ao;
    vec3 colour = tone_map(direct + ambient);

    // Analytic coverage of the silhouette (about one pixel wide), blended with the background in linear light.
    float coverage = clamp((1.0 - r) / pixel + 0.5, 0.0, 1.0);
    o_colour = vec4(mix(u_background, colour, coverage), 1.0);
}
"""


@dataclass(frozen=True)
class PreviewImages:
    """The rendered panels and what the figure says about them.

    decoded / original: (size, size, 3) float32, upright (row 0 = top), sRGB-encoded in [0, 1]; `original` is
    None without a source material. compressed_bytes: the BC6H payload of the four feature textures plus the
    decoder weights (GPU memory). psnr_all: report.json's aggregate PSNR (all textures, all mips), if the
    folder has one. notes: non-fatal observations (source files that differ from the compressed ones, ...).
    """

    decoded: np.ndarray
    original: Optional[np.ndarray]
    material: str
    compressed_bytes: int
    psnr_all: Optional[float]
    light: tuple[float, float]
    renderer: str
    notes: tuple[str, ...]


def _light_direction(azimuth: float, elevation: float) -> tuple[float, float, float]:
    """Unit vector towards the light in view space (x right, y up, z towards the camera): azimuth 0 is from the
    camera, positive to the right; elevation 0 is the horizon, 90 straight above."""
    az, el = math.radians(azimuth), math.radians(elevation)
    return (math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az))


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def source_mismatches(manifest: "Manifest", source: MaterialSource) -> list[str]:
    """Differences between the files a material was compressed from and the files given as its source: the
    preview still renders (the user may compare on purpose), but the comparison is then not like for like."""
    compressed = {f.role: f for f in manifest.material.files}
    given = {f.role: f for f in source.files}
    notes = []
    for role in sorted(set(compressed) | set(given)):
        was, now = compressed.get(role), given.get(role)
        if was is None and now is not None:
            notes.append(f"the source has a {role} map ({now.name}) the compressed material was made without")
        elif now is None and was is not None:
            notes.append(f"the source lacks the {role} map the compressed material was made from ({was.name})")
        elif was is not None and now is not None and was.sha256 != now.sha256:
            notes.append(f"source {role} {now.name} differs from the compressed {was.name} (SHA-256 "
                         f"{now.sha256[:12]}... vs {was.sha256[:12]}...)")
    if (source.width, source.height) != (manifest.width, manifest.height):
        notes.append(f"the source is {source.width}x{source.height}, the compressed material "
                     f"{manifest.width}x{manifest.height}")
    if source.normal_convention != manifest.material.normal_convention:
        notes.append(f"the source's normal map is {source.normal_convention}, the compressed material's "
                     f"{manifest.material.normal_convention}; each is rendered in its own convention")
    return notes


def _render_sphere(context: gl.HeadlessGL, lookup: str, textures: dict[str, Any], size: int,
                   light: tuple[float, float], normal_convention: str, address: str) -> np.ndarray:
    """One sphere panel with `lookup` (a GLSL `bcf_decode_grad`) as the material: (size, size, 3) sRGB."""
    fine = size * SUPERSAMPLE
    uniforms = {
        "u_size": (float(fine), float(fine)),
        "u_light": _light_direction(*light),
        # Clamped (atlas) materials are not meant to repeat: show them once around the sphere.
        "u_tiling": TILING if address == "wrap" else (1.0, 1.0),
        "u_normal_y": -1.0 if normal_convention == "directx" else 1.0,
        "u_tilt": math.radians(TILT_DEGREES),
        "u_radius": RADIUS,
        "u_background": tuple(float(v) for v in _srgb_to_linear(np.array(BACKGROUND))),
    }
    (rgba,) = context.render("#version 330 core\n" + lookup + _SHADING, (fine, fine), textures, uniforms)
    linear = rgba[..., :3].astype(np.float64).reshape(size, SUPERSAMPLE, size, SUPERSAMPLE, 3).mean(axis=(1, 3))
    # GL's row 0 is the bottom of the viewport; images have row 0 at the top.
    return _linear_to_srgb(linear[::-1]).astype(np.float32)


def _psnr_from_report(folder: Path, notes: list[str]) -> Optional[float]:
    from bcf.core import REPORT_FILE, ReportError, read_report

    if not (folder / REPORT_FILE).is_file():
        return None
    try:
        return float(read_report(folder).aggregate.psnr.all)
    except ReportError as exc:  # a preview does not need the scores: say so and go on
        notes.append(f"no PSNR in the title: {exc}")
        return None


def render_preview(folder: Path, source: Optional[Path] = None, size: int = 512,
                   light: tuple[float, float] = DEFAULT_LIGHT) -> PreviewImages:
    """Render the compressed material of the export folder `folder` on a lit sphere (and, with `source`, the
    material folder it came from, the same way). Raises ExportError for a bad folder,
    MaterialError for a bad source, gl.GLUnavailable without headless OpenGL, ValueError for a size
    outside [MIN_SIZE, MAX_SIZE]."""
    from bcf.core import read_manifest
    from bcf.engine.shader import shader_source

    if not MIN_SIZE <= size <= MAX_SIZE:
        raise ValueError(f"size must be in [{MIN_SIZE}, {MAX_SIZE}], got {size}")
    folder = Path(folder)
    decoder_glsl = shader_source(folder, "glsl")  # reads and checks every file of the folder (SHA-256 included)
    manifest = read_manifest(folder)
    notes: list[str] = []
    psnr_all = _psnr_from_report(folder, notes)
    texture_set = None
    if source is not None:
        texture_set = load_material(Path(source))
        # Only how the source differs from what was compressed: its discovery notes (which name 'bcf compress'
        # options) were shown when it was compressed.
        notes += source_mismatches(manifest, texture_set.source)
    compressed = sum(t.bytes for t in manifest.feature_textures) + manifest.decoder.bytes

    with gl.HeadlessGL() as context:
        features = {f"bcf_T{i}": context.bc6h_texture(read_dds(folder / t.file), manifest.address)
                    for i, t in enumerate(manifest.feature_textures)}
        decoded = _render_sphere(context, decoder_glsl, features, size, light,
                                 manifest.material.normal_convention, manifest.address)
        original = None
        if texture_set is not None:
            # The stored channels as float textures, mipmapped by the driver's box filter (bcf's material mips
            # are box-filtered too); row 0 at t = 0 like the BC6H uploads, so both panels map alike.
            c = texture_set.channels
            textures = {name: context.float_texture(c[..., channels], manifest.address)
                        for name, channels in (("src_albedo", TEXTURES["albedo"]),
                                               ("src_normal", TEXTURES["normal"]),
                                               ("src_arm", TEXTURES["arm"]))}
            original = _render_sphere(context, _SOURCE_LOOKUP, textures, size, light,
                                      texture_set.source.normal_convention, manifest.address)
        renderer = context.renderer
    return PreviewImages(decoded=decoded, original=original, material=manifest.material.name,
                         compressed_bytes=compressed, psnr_all=psnr_all, light=(float(light[0]), float(light[1])),
                         renderer=renderer, notes=tuple(notes))


# ------------------------------------------------------------------------------------------------ figure

_FIGURE_BACKGROUND = "#121212"  # darker than the panels' BACKGROUND, so each panel reads as a square
_TEXT = "#e6e6e6"
_DPI = 100
_MARGIN_PX = 16  # around and between the panels
_TITLE_PX = 28  # one line of panel title
_SUPTITLE_PX = 34  # the material line on top


def panel_titles(images: PreviewImages) -> list[str]:
    titles = [f"bcf ({images.compressed_bytes / 1024:.1f} KiB)"]
    return titles + (["original textures"] if images.original is not None else [])


def _suptitle(images: PreviewImages) -> str:
    text = images.material
    if images.psnr_all is not None:
        text += f": aggregate PSNR {images.psnr_all:.2f} dB"
    return text


def panel_boxes(size: int, panels: int) -> tuple[tuple[int, int], list[tuple[int, int]]]:
    """The figure's (width, height) in pixels and each panel's (left, top) pixel: panels are drawn 1:1, so the
    PNG holds the rendered pixels unscaled (and tests can find them)."""
    width = panels * size + (panels + 1) * _MARGIN_PX
    height = _SUPTITLE_PX + _TITLE_PX + size + _MARGIN_PX
    top = _SUPTITLE_PX + _TITLE_PX
    return (width, height), [(_MARGIN_PX + i * (size + _MARGIN_PX), top) for i in range(panels)]


def write_preview(images: PreviewImages, path: Path) -> Path:
    """Compose the panels into one PNG at `path` (written through a temporary file, so a failure leaves no
    partial image); returns `path`."""
    import matplotlib

    matplotlib.use("Agg")  # no display needed, and no GUI toolkit imported
    from matplotlib.figure import Figure  # a bare Figure: no pyplot state shared with a caller

    panels: Sequence[np.ndarray] = [images.decoded] + ([images.original] if images.original is not None else [])
    size = images.decoded.shape[0]
    (width, height), boxes = panel_boxes(size, len(panels))
    figure = Figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI, facecolor=_FIGURE_BACKGROUND)
    for image, title, (left, top) in zip(panels, panel_titles(images), boxes):
        axes = figure.add_axes((left / width, 1 - (top + size) / height, size / width, size / height))
        axes.imshow(np.clip(image, 0.0, 1.0), interpolation="none")
        axes.set_axis_off()
        axes.set_title(title, color=_TEXT, fontsize=11, pad=6)
    figure.suptitle(_suptitle(images), color=_TEXT, fontsize=12, y=1 - 8 / height, va="top")
    with atomic_path(Path(path)) as temporary:
        figure.savefig(temporary, dpi=_DPI, facecolor=_FIGURE_BACKGROUND, format="png")
    return Path(path)
