"""report.html (`html_report`): a self-contained page built from a real compression of tests/data/chainmail_128.

The report comes from `compress.compress_material` with a short schedule; the crops are real decodes of the
export. A second method, "half_resolution" (each reference mip box-filtered to half size and shown with nearest
upsampling), is scored with the same `metrics.evaluate` as ours, so every number on the page is measured. The
page is checked as text (no external references, valid embedded PNGs, escaping) and rendered in headless
Chromium (no console errors, every image decoded, a screenshot with real content).
"""

from __future__ import annotations

import base64
import io
import re
import shutil
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from matplotlib.image import imread

from bcf.core import files, load_export
from bcf.core import pipeline as compress
from bcf.core.report import html as html_report
from bcf.core.report import metrics
from bcf.core.report import report_json as report
from bcf.core.report.html import HTML_REPORT_FILE, Crop, render_html_report, write_html_report
from bcf.core.material.texture_set import TextureSet, load_material
from bcf.core.options import CompressOptions
from bcf.core.fit.sampling import ReferenceMaterial

CHAINMAIL = Path(__file__).resolve().parent / "data" / "chainmail_128"
OPTIONS = CompressOptions(preset="fast", phase1_iterations=100, phase2_iterations=100, batch_size=4096)
CHROMIUM = Path("/usr/bin/chromium")
# Switches that keep a headless Chromium quiet and offline in a container (root: no sandbox; no GPU there).
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
CROPS = ((0, 40, 24, 32), (1, 0, 0, 32))  # (mip, x, y, size)


# ------------------------------------------------------------------------------------------------ helpers


def half_resolution(mip: torch.Tensor) -> torch.Tensor:
    """(C, h, w) -> the 2x2 box average shown at full size (nearest): a real, honestly scored degradation."""
    _, h, w = mip.shape
    if h < 2 or w < 2:
        return mip.clone()
    small = F.avg_pool2d(mip.unsqueeze(0), 2)
    return F.interpolate(small, size=(h, w), mode="nearest")[0]


class HalfResolution:
    """A metrics.Decoder returning the half-resolution image of the reference mip s at the texel under uv."""

    def __init__(self, reference: ReferenceMaterial):
        started = time.perf_counter()
        self.images = [half_resolution(reference.mip(level)) for level in range(reference.levels)]
        self.encode_s = time.perf_counter() - started

    def __call__(self, uv: torch.Tensor, s: float) -> torch.Tensor:
        image = self.images[int(s)]
        _, h, w = image.shape
        x = (uv[:, 0] * w).long().clamp(0, w - 1)
        y = (uv[:, 1] * h).long().clamp(0, h - 1)
        return image[:, y, x].T


def half_resolution_baseline(texture_set: TextureSet, reference: ReferenceMaterial,
                             decoder: HalfResolution) -> report.BaselineReport:
    """Scores from metrics.evaluate, like ours; size: 8 channels of 8 bits at half size, all mips."""
    started = time.perf_counter()
    scores = metrics.evaluate(decoder, reference)
    evaluation_s = time.perf_counter() - started
    sizes = [(m.shape[2], m.shape[1]) for m in reference.mips]
    evaluation = report.summarise(scores, sizes)
    size_bytes = sum(max(1, w // 2) * max(1, h // 2) * 8 for w, h in sizes)
    return report.BaselineReport(
        description="reference mips box-filtered to half size, nearest upsampling, 8 bits per channel",
        encoder="torch avg_pool2d (test stand-in, not a codec)", width=texture_set.width // 2,
        height=texture_set.height // 2, aggregate=evaluation.aggregate, per_mip=evaluation.per_mip,
        size_bytes=size_bytes, bits_per_texel=size_bytes * 8 / (texture_set.width * texture_set.height),
        encode_s=decoder.encode_s, evaluation_s=evaluation_s)


def hwc(image: torch.Tensor) -> np.ndarray:
    return image.clamp(0.0, 1.0).permute(1, 2, 0).numpy().astype(np.float32)


def img_sources(page: str) -> list[str]:
    return re.findall(r'<img\b[^>]*\bsrc="([^"]*)"', page)


def decode_png(data: bytes) -> np.ndarray:
    assert data.startswith(PNG_SIGNATURE), data[:16]
    return imread(io.BytesIO(data), format="png")


# ----------------------------------------------------------------------------------------------- fixtures


class Material:
    """The chainmail compressed once: its report with and without the half-resolution baseline, and crops."""

    def __init__(self, texture_set: TextureSet, folder: Path, rep: report.Report):
        reference = ReferenceMaterial(texture_set.channels, rep.options.address)
        half = HalfResolution(reference)
        self.report = rep
        self.with_baseline = rep.model_copy(
            update={"baselines": {"half_resolution": half_resolution_baseline(texture_set, reference, half)}})
        model = load_export(folder).model
        self.crops: list[Crop] = []
        self.ours_only: list[Crop] = []
        for mip, x, y, size in CROPS:
            target = reference.mip(mip)
            _, h, w = target.shape
            region = (slice(y, y + size), slice(x, x + size))
            ours = hwc(metrics.render_mip(model, w, h, float(mip)))[region]
            ref = hwc(target)[region]
            halved = hwc(half.images[mip])[region]
            self.crops.append(Crop(mip, x, y, size, ref, {"ours": ours, "half_resolution": halved}))
            self.ours_only.append(Crop(mip, x, y, size, ref, {"ours": ours}))


@pytest.fixture(scope="module")
def material(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Material]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        texture_set = load_material(CHAINMAIL)
        folder = tmp_path_factory.mktemp("html") / "out"
        rep = compress.compress_material(texture_set, OPTIONS, folder)
        yield Material(texture_set, folder, rep)
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def page(material: Material) -> str:
    return render_html_report(material.with_baseline, material.crops)


# ------------------------------------------------------------------------------------------ the page as text


def test_page_references_nothing_outside_itself(page: str) -> None:
    assert not re.search(r"https?://", page), re.search(r".{60}https?://.{60}", page)
    references = re.findall(r'\b(?:src|href|action|poster|data)\s*=\s*"([^"]*)"', page)
    assert references and all(r.startswith("data:image/png;base64,") for r in references), \
        [r[:60] for r in references if not r.startswith("data:")]
    assert "url(" not in page and "@import" not in page
    assert "<script" not in page.lower()
    assert "<link" not in page.lower()


def test_every_image_is_an_embedded_png(page: str, material: Material) -> None:
    sources = img_sources(page)
    assert len(sources) == page.count("<img")
    # 2 charts, the legend ramp; per crop 3 reference images and 3 x (image + error map) per method.
    assert len(sources) == 3 + sum(3 + 3 * 2 * len(c.methods) for c in material.crops)
    for source in sources:
        prefix = "data:image/png;base64,"
        assert source.startswith(prefix), source[:60]
        pixels = decode_png(base64.b64decode(source[len(prefix):], validate=True))
        assert pixels.shape[0] > 0 and pixels.shape[1] > 0
        assert np.ptp(pixels) > 0, "a blank image"


def test_page_shows_the_measured_numbers(page: str, material: Material) -> None:
    rep = material.with_baseline
    baseline = rep.baselines["half_resolution"]
    assert f"<h1>{rep.material.name}</h1>" in page
    assert f"<title>{rep.material.name}" in page
    for value in (rep.aggregate.psnr.all, rep.aggregate.psnr.albedo, rep.aggregate.psnr.normal,
                  rep.aggregate.psnr.arm, baseline.aggregate.psnr.all, rep.mean_baseline.psnr.all,
                  rep.jittered.aggregate.psnr.all, *(m.psnr.all for m in rep.per_mip)):
        assert f">{value:.2f}<" in page, value
    assert f"{rep.aggregate.ssim.all:.4f}" in page
    for name in ("half_resolution", *rep.models, rep.device, rep.created_at, rep.generator,
                 f"{rep.size.total_bytes:,}", f"{rep.size.bc1_bc5_bytes:,}", f"preset {rep.options.preset}",
                 f"block mode {rep.options.block_mode}", f"{rep.material.width} x {rep.material.height}"):
        assert str(name) in page, name
    assert "mip 0 of 128 x 128: texels x 40&ndash;71, y 24&ndash;55" in page
    assert "mip 1 of 64 x 64: texels x 0&ndash;31, y 0&ndash;31" in page
    # The crop PSNRs shown are the crop's own (recomputed here from the same arrays).
    crop = material.crops[0]
    diff = crop.methods["ours"][..., 0:3].astype(np.float64) - crop.reference[..., 0:3]
    assert f"{metrics.psnr_from_mse(float(np.mean(diff**2))):.2f} dB" in page


def test_summary_is_sorted_by_size(page: str, material: Material) -> None:
    rep = material.with_baseline
    summary = page[page.index("<h2>Summary</h2>"):page.index("<h3>Other evaluations")]
    sizes = {"ours": rep.size.total_bytes, "half_resolution": rep.baselines["half_resolution"].size_bytes}
    expected = sorted(sizes.items(), key=lambda item: item[1])
    positions = [summary.index(f">{name}<") for name, _ in expected]
    assert positions == sorted(positions)


def test_strings_are_escaped(material: Material) -> None:
    rep = material.with_baseline
    nasty = '<script>alert("x")</script>&'
    source = rep.material.model_copy(update={"name": nasty})
    baseline = rep.baselines["half_resolution"].model_copy(update={"description": "<b>bold</b>", "encoder": "<i>"})
    rep = rep.model_copy(update={"material": source, "baselines": {"<img src=x>": baseline}})
    crop = material.crops[0]
    crops = [Crop(crop.mip, crop.x, crop.y, crop.size, crop.reference, {"ours": crop.methods["ours"],
                                                                         "<em>evil</em>": crop.reference})]
    page = render_html_report(rep, crops)
    assert "<script" not in page and "<b>bold" not in page and "<i>" not in page and "<em>" not in page
    assert "<img src=x>" not in page
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt;&amp;" in page
    assert "&lt;img src=x&gt;" in page and "&lt;em&gt;evil&lt;/em&gt;" in page


def test_page_without_baselines(material: Material) -> None:
    assert material.report.baselines == {}
    page = render_html_report(material.report, material.ours_only)
    assert "half_resolution" not in page and "<h3>Baselines</h3>" not in page
    assert f">{material.report.aggregate.psnr.all:.2f}<" in page
    assert len(img_sources(page)) == 3 + sum(3 + 3 * 2 for _ in material.ours_only)
    # And without crops at all: the tables and charts alone.
    bare = render_html_report(material.report, [])
    assert "<h2>Crops</h2>" not in bare and len(img_sources(bare)) == 2


def test_crop_shapes_are_checked(material: Material) -> None:
    crop = material.crops[0]
    with pytest.raises(ValueError, match="half_resolution has shape"):
        Crop(crop.mip, crop.x, crop.y, crop.size, crop.reference, {"half_resolution": crop.reference[:-1]})


def test_write_is_atomic(material: Material, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / HTML_REPORT_FILE
    path.write_text("old page")
    write_html_report(path, material.report, [])
    first = path.read_text(encoding="utf-8")
    assert first.startswith("<!DOCTYPE html>") and first == render_html_report(material.report, [])
    assert path.stat().st_mode & 0o777 == 0o644

    def fail(*_: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", fail)  # the one atomic write, `bcf.core.files.atomic_path`
    with pytest.raises(OSError, match="disk full"):
        write_html_report(path, material.report, material.ours_only)
    assert path.read_text(encoding="utf-8") == first, "a failed write must leave the previous page"
    assert sorted(p.name for p in tmp_path.iterdir()) == [HTML_REPORT_FILE], "temporary file left behind"


# -------------------------------------------------------------------------------------- headless Chromium


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    # Fail, never skip: CI installs Chromium (.ci/run) and playwright (the dev extra); a missing one must show.
    if not CHROMIUM.is_file() and shutil.which("chromium") is None:
        pytest.fail(f"{CHROMIUM} not found: the report.html rendering test needs Debian's chromium package "
                    "(apt-get install chromium; .ci/run installs it)", pytrace=False)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        pytest.fail(f"python playwright is required (pip install -e '.[dev]'): {exc}", pytrace=False)
    executable = str(CHROMIUM) if CHROMIUM.is_file() else shutil.which("chromium")
    with sync_playwright() as playwright:
        # Debian's Chromium, not playwright's own download: `playwright install` is never run.
        launched = playwright.chromium.launch(executable_path=executable, headless=True, args=CHROMIUM_ARGS)
        try:
            yield launched
        finally:
            launched.close()


@pytest.mark.parametrize("which", ["with_baseline", "ours_only"])
def test_page_renders_in_chromium(material: Material, browser: object, tmp_path: Path, which: str) -> None:
    if which == "with_baseline":
        rep, crops = material.with_baseline, material.crops
    else:
        rep, crops = material.report, material.ours_only
    path = tmp_path / HTML_REPORT_FILE
    write_html_report(path, rep, crops)

    page = browser.new_page(viewport={"width": 1280, "height": 900})  # type: ignore[attr-defined]
    errors: list[str] = []
    requests: list[str] = []
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("request", lambda request: requests.append(request.url))
    page.goto(path.as_uri(), wait_until="load")

    assert errors == []
    assert all(url.startswith(("file://", "data:")) for url in requests), requests
    images = page.evaluate("Array.from(document.images).map(i => [i.complete, i.naturalWidth, i.naturalHeight])")
    assert len(images) == len(img_sources(path.read_text(encoding="utf-8")))
    assert all(complete and width > 0 and height > 0 for complete, width, height in images), images
    height = page.evaluate("document.documentElement.scrollHeight")
    assert height > 1500, height  # header, tables, two charts, two crop grids
    assert page.evaluate("document.documentElement.scrollWidth") <= 1280, "the page scrolls sideways"

    shot = page.screenshot(full_page=True)
    page.close()
    (tmp_path / "screenshot.png").write_bytes(shot)  # kept in pytest's temp folder for a human to look at
    pixels = decode_png(shot)
    assert pixels.shape[0] == height and pixels.shape[1] == 1280
    rgb = np.round(pixels[..., :3] * 255).astype(np.uint32)
    colours = np.unique((rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2])  # packed: unique(axis=0) is slow
    assert len(colours) > 2000, len(colours)  # text, charts and material crops, not a blank or flat page
