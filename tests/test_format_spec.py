"""docs/FORMAT.md, checked by a decoder written from the document alone.

`SpecDecoder` below knows only what FORMAT.md says: it reads manifest.json with `json`, the feature textures with
OpenImageIO (a BC6H decoder independent of bcf's), decoder.bin with numpy, and does the bilinear / trilinear
lookups and the MLP in float64 numpy. It must reproduce what `bcf decode` writes (run as a subprocess on a
`bcf compress` output of a crop of examples/sample) to half-float precision, and what bcf's own reference
decoder computes at arbitrary points and scales. The python reference in FORMAT.md is run too, and the folder
layout, DDS headers, manifest and report.json are checked field by field against the document.

Two exports: `wrap`, a non-square 128x64 crop with 1k features (wrap addressing, every T_i non-square), and
`clamp`, a 64x64 crop with 0.5k features and --address clamp (T2 and T3 both 4x4 with a single mip, so
lod_bias comes from the 4-texel floor).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from bcf_command import run_bcf
from reference_decoders import decode_with_oiio, oiio_mip_sizes

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "FORMAT.md"
SAMPLE = ROOT / "examples" / "sample"
SOURCE_FILES = ("albedo.png", "normal_gl.png", "arm.png")  # RGB each: albedo, normal (x, y, z), AO/rough/metal
FEATURE_SCALE = {"0.5k": 0.25, "1k": 0.5, "2k": 1.0}  # FORMAT.md, "Sizes and coordinates"
RENDER_FILES = {f"features_{i}.dds" for i in range(4)} | {"decoder.bin", "manifest.json"}
HALF_TOLERANCE = 1e-3  # > 1 half ulp at [0.5, 1] (4.9e-4): the EXRs are half floats


def run_bcf_ok(*args: object) -> None:
    result = run_bcf(*args, timeout=300)
    assert result.returncode == 0, f"bcf {' '.join(map(str, args))} failed:\n{result.stdout}\n{result.stderr}"


# ------------------------------------------------------------------------------------ the material


def read_uint8(path: Path) -> np.ndarray:
    image = oiio.ImageInput.open(str(path))
    assert image is not None, oiio.geterror()
    pixels = image.read_image(0, 0, 0, 3, "uint8")
    image.close()
    return pixels


def write_uint8(path: Path, pixels: np.ndarray) -> None:
    height, width, channels = pixels.shape
    output = oiio.ImageOutput.create(str(path))
    assert output is not None and output.open(str(path), oiio.ImageSpec(width, height, channels, "uint8"))
    assert output.write_image(np.ascontiguousarray(pixels)), output.geterror()
    output.close()


def read_exr(path: Path) -> np.ndarray:
    image = oiio.ImageInput.open(str(path))
    assert image is not None, oiio.geterror()
    pixels = image.read_image(0, 0, 0, 3, "float")
    image.close()
    return np.asarray(pixels, dtype=np.float64)


@dataclass(frozen=True)
class Export:
    name: str
    folder: Path  # bcf compress output
    decoded: Path  # bcf decode --all-mips --format exr output
    stored: np.ndarray  # (H, W, 8) source values as stored, in [0, 1]: albedo RGB, normal x y, ARM


CASES = {
    # name: (crop rows, crop columns, extra compress arguments)
    "wrap": (slice(0, 64), slice(0, 128), ["--features", "1k"]),
    "clamp": (slice(96, 160), slice(32, 96), ["--features", "0.5k", "--address", "clamp"]),
}


@pytest.fixture(scope="module", params=list(CASES))
def export(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Export:
    rows, columns, extra = CASES[request.param]
    base = tmp_path_factory.mktemp(f"format_{request.param}")
    material = base / "material"
    material.mkdir()
    crops = {}
    for name in SOURCE_FILES:
        crops[name] = read_uint8(SAMPLE / name)[rows, columns]
        write_uint8(material / name, crops[name])
    stored = np.concatenate([crops["albedo.png"], crops["normal_gl.png"][..., :2], crops["arm.png"]], axis=2)
    folder, decoded = base / "out", base / "decoded"
    run_bcf_ok("compress", material, "-o", folder, "--preset", "fast", "--phase1-iterations", 60,
            "--phase2-iterations", 60, "--batch-size", 4096, "-q", *extra)
    run_bcf_ok("decode", folder, "-o", decoded, "--all-mips", "--format", "exr")
    return Export(request.param, folder, decoded, stored.astype(np.float64) / 255.0)


# ----------------------------------------------------------------- the decoder, from FORMAT.md alone


class SpecDecoder:
    """FORMAT.md's decode steps 1-5 in float64 numpy; feature texels decoded by OpenImageIO."""

    def __init__(self, folder: Path):
        self.manifest = m = json.loads((folder / "manifest.json").read_text())
        self.address = m["address"]
        self.textures = []  # (entry, [level (h, w, 3) float64, ...])
        for entry in m["feature_textures"]:
            levels = [decode_with_oiio(folder / entry["file"], level).astype(np.float64)
                      for level in range(entry["mips"])]
            self.textures.append((entry, levels))
        values = np.frombuffer((folder / m["decoder"]["file"]).read_bytes(), dtype="<f2").astype(np.float64)
        self.layers = []
        for layer in m["decoder"]["layers"]:
            n_in, n_out = layer["inputs"], layer["outputs"]
            weight = values[layer["weight_offset"]:layer["weight_offset"] + n_out * n_in].reshape(n_out, n_in)
            bias = values[layer["bias_offset"]:layer["bias_offset"] + n_out]
            self.layers.append((weight, bias, layer["activation"]))

    def _tap(self, index: np.ndarray, size: int) -> np.ndarray:
        if self.address == "wrap":
            return np.mod(index, size)
        return np.clip(index, 0, size - 1)

    def bilinear(self, level: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        h, w, _ = level.shape
        x, y = u * w - 0.5, v * h - 0.5
        fx, fy = np.floor(x), np.floor(y)
        ax, ay = (x - fx)[:, None], (y - fy)[:, None]
        x0, y0 = fx.astype(np.int64), fy.astype(np.int64)
        xa, xb = self._tap(x0, w), self._tap(x0 + 1, w)
        ya, yb = self._tap(y0, h), self._tap(y0 + 1, h)
        return ((1 - ay) * ((1 - ax) * level[ya, xa] + ax * level[ya, xb])
                + ay * ((1 - ax) * level[yb, xa] + ax * level[yb, xb]))

    def trilinear(self, levels: list[np.ndarray], u: np.ndarray, v: np.ndarray, lod: float) -> np.ndarray:
        lod = min(max(lod, 0.0), len(levels) - 1.0)
        l0 = int(math.floor(lod))
        l1 = min(l0 + 1, len(levels) - 1)
        t = lod - l0
        value = self.bilinear(levels[l0], u, v)
        return value if t == 0 else (1 - t) * value + t * self.bilinear(levels[l1], u, v)

    def raw(self, u: np.ndarray, v: np.ndarray, s: float) -> np.ndarray:
        """The 8 MLP outputs before saturation at points (u, v) and material scale s."""
        x = np.zeros((u.size, 12))
        for entry, levels in self.textures:
            x[:, entry["mlp_inputs"]] = self.trilinear(levels, u, v, s + entry["lod_bias"])
        for weight, bias, activation in self.layers:
            x = x @ weight.T + bias
            if activation == "relu":
                x = np.maximum(x, 0.0)
        return x

    def images(self, mip: int) -> dict[str, np.ndarray]:
        """What `bcf decode` writes for material mip `mip`: texel centres, s = mip, saturated, z rebuilt."""
        m = self.manifest
        w, h = m["width"] >> mip, m["height"] >> mip
        u, v = texel_centres(w, h)
        y = np.clip(self.raw(u, v, float(mip)), 0.0, 1.0).reshape(h, w, 8)
        outputs = {o["name"]: o["channels"] for o in m["outputs"]}
        n = y[..., outputs["normal"]] * 2 - 1
        z = np.sqrt(np.clip(1 - (n**2).sum(-1, keepdims=True), 0.0, 1.0))
        return {"albedo": y[..., outputs["albedo"]], "normal": np.concatenate([y[..., outputs["normal"]],
                                                                             (z + 1) / 2], -1),
                "arm": y[..., outputs["arm"]]}


def texel_centres(w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return ((x + 0.5) / w).ravel(), ((y + 0.5) / h).ravel()


def decoded_name(texture: str, mip: int) -> str:
    return f"{texture}.exr" if mip == 0 else f"{texture}_mip{mip}.exr"


@pytest.fixture(scope="module")
def decoder(export: Export) -> SpecDecoder:
    return SpecDecoder(export.folder)


def checked_mips(manifest: dict) -> list[int]:
    return sorted({0, 1, manifest["mips"] - 1})


# ------------------------------------------------------------------------------------------- tests


def test_numpy_decoder_matches_bcf_decode(export: Export, decoder: SpecDecoder) -> None:
    m = decoder.manifest
    expected = {decoded_name(t, mip) for t in ("albedo", "normal", "arm") for mip in range(m["mips"])}
    assert {p.name for p in export.decoded.iterdir()} == expected
    for mip in checked_mips(m):
        for texture, mine in decoder.images(mip).items():
            theirs = read_exr(export.decoded / decoded_name(texture, mip))
            assert theirs.shape == ((m["height"] >> mip), (m["width"] >> mip), 3)
            error = np.abs(np.clip(theirs, 0, 1) - mine).max()
            assert error < HALF_TOLERANCE, f"{export.name} mip {mip} {texture}: max |diff| {error:.2e}"


def test_numpy_decoder_matches_bcf_at_any_point_and_scale(export: Export, decoder: SpecDecoder) -> None:
    """Fractional scales (both trilinear taps), points anywhere (addressing), before saturation: against
    bcf's reference decoder built from the same files (not used by SpecDecoder)."""
    import torch

    from bcf.core import load_export

    model = load_export(export.folder).model
    m = decoder.manifest
    rng = np.random.default_rng(1)
    low, high = (-1.5, 2.5) if m["address"] == "wrap" else (-0.25, 1.25)
    uv = rng.uniform(low, high, (2000, 2)).astype(np.float32)
    scales = [-0.5, 0.0, 0.37, 1.5, m["mips"] - 1.25, m["mips"] - 1.0, m["mips"] + 0.5]
    for s in scales:
        mine = decoder.raw(uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64), s)
        with torch.no_grad():
            theirs = model(torch.from_numpy(uv), s).numpy()
        error = np.abs(mine - theirs).max()
        assert error < 1e-4, f"{export.name} s = {s}: max |diff| {error:.2e}"


def test_python_reference_in_the_document_matches_bcf_decode(export: Export) -> None:
    match = re.search(r"#### Reference \(numpy\).*?```python\n(.*?)```", DOC.read_text(), re.S)
    assert match, "FORMAT.md has no python block under '#### Reference (numpy)'"
    namespace: dict = {}
    exec(compile(match.group(1), f"{DOC}:reference", "exec"), namespace)
    m, layers = namespace["load_decoder"](str(export.folder))
    features = [[decode_with_oiio(export.folder / t["file"], level).astype(np.float32) for level in range(t["mips"])]
                for t in m["feature_textures"]]
    for mip in checked_mips(m):
        w, h = m["width"] >> mip, m["height"] >> mip
        u, v = texel_centres(w, h)
        out = namespace["decode"](m, layers, features, u, v, float(mip))
        normal = (out["normal"] + 1) / 2  # bcf decode stores (n + 1) / 2, z included
        for texture, mine in {"albedo": out["albedo"], "normal": normal, "arm": out["arm"]}.items():
            theirs = read_exr(export.decoded / decoded_name(texture, mip))
            error = np.abs(theirs - mine.reshape(h, w, 3)).max()
            assert error < HALF_TOLERANCE, f"{export.name} mip {mip} {texture}: max |diff| {error:.2e}"


def test_folder_dds_files_and_manifest_follow_the_document(export: Export) -> None:
    folder = export.folder
    assert {p.name for p in folder.iterdir()} == RENDER_FILES | {"report.json", "report.html"}
    m = json.loads((folder / "manifest.json").read_text())
    assert (m["format"], m["format_version"]) == ("bcf-neural-material", 1)
    W, H = m["width"], m["height"]
    assert (W, H) == (export.stored.shape[1], export.stored.shape[0])
    assert (m["material"]["width"], m["material"]["height"]) == (W, H)
    assert m["mips"] == int(math.log2(min(W, H))) - 1
    assert m["address"] == m["options"]["address"] == ("clamp" if export.name == "clamp" else "wrap")
    f = FEATURE_SCALE[m["options"]["features"]]
    assert len(m["feature_textures"]) == 4
    for i, t in enumerate(m["feature_textures"]):
        w, h = max(4, int(W * f) >> i), max(4, int(H * f) >> i)
        assert (t["file"], t["format"], t["dxgi_format"]) == (f"features_{i}.dds", "BC6H_UF16", 95)
        assert (t["width"], t["height"], t["mips"]) == (w, h, int(math.log2(min(w, h))) - 1)
        assert t["lod_bias"] == math.log2(max(w / W, h / H))
        assert t["mlp_inputs"] == [3 * i, 3 * i + 1, 3 * i + 2]
        sizes = [(w >> level, h >> level) for level in range(t["mips"])]
        assert min(sizes[-1]) == 4 and all(a % 4 == 0 and b % 4 == 0 for a, b in sizes)
        assert t["bytes"] == sum(a // 4 * (b // 4) * 16 for a, b in sizes)
        data = (folder / t["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == t["sha256"]
        assert data[:4] == b"DDS " and len(data) == 148 + t["bytes"]
        size, flags, height, width, _, _, mip_count = struct.unpack_from("<7I", data, 4)
        assert (size, flags, height, width, mip_count) == (124, 0x000A1007, h, w, t["mips"])
        assert struct.unpack_from("<5I", data, 128) == (95, 3, 0, 1, 0)
        assert oiio_mip_sizes(folder / t["file"]) == sizes
        # Eq. 11: the hardware LOD from T_i's own size is s + lod_bias whenever the LOD matters (> 1 mip).
        if t["mips"] > 1:
            rng = np.random.default_rng(i)
            for dx, dy in rng.uniform(-0.05, 0.05, (20, 2, 2)):
                s = math.log2(max(np.hypot(dx[0] * W, dx[1] * H), np.hypot(dy[0] * W, dy[1] * H)))
                s_i = math.log2(max(np.hypot(dx[0] * w, dx[1] * h), np.hypot(dy[0] * w, dy[1] * h)))
                assert s_i == pytest.approx(s + t["lod_bias"], abs=1e-9)

    d = m["decoder"]
    data = (folder / d["file"]).read_bytes()
    assert (d["file"], d["dtype"], d["byte_order"]) == ("decoder.bin", "float16", "little")
    assert len(data) == d["bytes"] and hashlib.sha256(data).hexdigest() == d["sha256"]
    hidden = m["options"]["hidden"]
    assert [(l["inputs"], l["outputs"], l["activation"]) for l in d["layers"]] == [(12, hidden, "relu"),
                                                                                  (hidden, 8, "identity")]
    offset = 0  # W1, b1, W2, b2 back to back
    for layer in d["layers"]:
        assert (layer["weight_offset"], layer["bias_offset"]) == (offset, offset + layer["inputs"] * layer["outputs"])
        offset = layer["bias_offset"] + layer["outputs"]
    assert 2 * offset == d["bytes"] == {16: 688, 32: 1360}[hidden]
    assert [(o["name"], o["channels"]) for o in m["outputs"]] == [("albedo", [0, 1, 2]), ("normal", [3, 4]),
                                                                  ("arm", [5, 6, 7])]


def box_pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    pyramid = [image]
    for _ in range(levels - 1):
        a = pyramid[-1]
        pyramid.append(a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2, -1).mean(axis=(1, 3)))
    return pyramid


def test_report_follows_the_document(export: Export, decoder: SpecDecoder) -> None:
    folder = export.folder
    m = decoder.manifest
    r = json.loads((folder / "report.json").read_text())
    W, H, M = m["width"], m["height"], m["mips"]

    size = r["size"]
    assert size["features_bytes"] == sum(t["bytes"] for t in m["feature_textures"])
    assert size["weights_bytes"] == m["decoder"]["bytes"]
    assert size["total_bytes"] == size["features_bytes"] + size["weights_bytes"]
    assert size["files_bytes"] == sum(p.stat().st_size for p in folder.iterdir())
    assert size["bits_per_texel"] == pytest.approx(size["total_bytes"] * 8 / (W * H))
    bc = sum(math.ceil(max(1, W >> l) / 4) * math.ceil(max(1, H >> l) / 4) * 32
             for l in range(max(W, H).bit_length()))
    assert size["bc1_bc5_bytes"] == bc

    groups = {"albedo": slice(0, 3), "normal": slice(3, 5), "arm": slice(5, 8), "all": slice(0, 8)}
    assert [(p["mip"], p["width"], p["height"]) for p in r["per_mip"]] == [(n, W >> n, H >> n) for n in range(M)]
    assert len(r["jittered"]["per_mip"]) == M
    for evaluation in (r, r["jittered"]):
        for name in groups:
            mean_mse = sum(p["mse"][name] for p in evaluation["per_mip"]) / M
            assert evaluation["aggregate"]["psnr"][name] == pytest.approx(-10 * math.log10(mean_mse))
            mean_ssim = sum(p["ssim"][name] for p in evaluation["per_mip"]) / M
            assert evaluation["aggregate"]["ssim"][name] == pytest.approx(mean_ssim)
    assert r["models"]["exported"] == r["aggregate"]
    assert set(r["models"]) == {"exported", "trained_fp32", "phase1_unconstrained"}

    # per_mip: our decoder at the texel centres of mip N (s = N), saturated, against the 2x2 box pyramid of
    # the stored source values.
    reference = box_pyramid(export.stored, M)
    for n in range(M):
        w, h = W >> n, H >> n
        u, v = texel_centres(w, h)
        mine = np.clip(decoder.raw(u, v, float(n)), 0.0, 1.0).reshape(h, w, 8)
        for name, channels in groups.items():
            mse = float(np.mean((mine[..., channels] - reference[n][..., channels]) ** 2))
            assert r["per_mip"][n]["mse"][name] == pytest.approx(mse, rel=1e-3, abs=1e-9), (n, name)
            assert r["per_mip"][n]["psnr"][name] == pytest.approx(-10 * math.log10(mse), abs=5e-3), (n, name)
