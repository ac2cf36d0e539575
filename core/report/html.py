"""report.html: one self-contained page showing a compressed material's report next to its baselines.

Everything the page shows comes from a `Report` (scores, sizes, times: the same numbers as report.json) plus a
few `Crop`s of decoded texels (`select_crops` picks and renders them). The page has no JavaScript and no external reference:
images and charts are PNGs embedded as data: URLs and the stylesheet is inline, so the file can be mailed,
archived or opened offline and looks the same.

Charts are drawn with matplotlib's object API (`Figure` + `FigureCanvasAgg`), never pyplot, so rendering a
page changes no global matplotlib state (backend, current figure) of the calling process.
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, NamedTuple, Optional, Sequence

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backend_bases import RendererBase
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import imsave
from matplotlib.text import Annotation
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from bcf.core.export.decode import DecoderFunction, render_region
from bcf.core.files import write_text_atomic
from bcf.core.fit.sampling import ReferenceMaterial
from bcf.core.material.roles import TEXTURES, material_images
from bcf.core.psnr import psnr_from_mse
from bcf.core.report.report_json import Aggregate, MipMetrics, Report

__all__ = ["HTML_REPORT_FILE", "Crop", "render_html_report", "select_crops", "write_html_report"]

HTML_REPORT_FILE = "report.html"

OURS = "ours"
CROP_TEXELS = (128, 64)  # sides of the crops at mip 0 and at the middle mip
# Methods shown in the crops beside ours (when they were run): the usual BC set at both sizes, ASTC at about
# our size, and what our phase 2 improves on.
CROP_BASELINES = ("bc1_bc5_full", "bc1_bc5_half", "astc_12x12_full", "astc_8x8_full", "naive_bc6")
MIB = float(1 << 20)
ERROR_MAX = 0.1  # heat maps saturate here: one fixed scale so maps of different methods compare directly
ERROR_CMAP = "inferno"
CROP_DISPLAY_PX = 160  # crops are enlarged by an integer factor to at least this many pixels
CHART_DPI = 100
OURS_COLOUR = "#c62828"
TEXTURE_TITLES = {"albedo": "Albedo", "normal": "Normal", "arm": "ARM (AO, roughness, metalness)"}


@dataclass(frozen=True, eq=False)  # eq=False: arrays have no single truth value, so compare by identity
class Crop:
    """A square region of one mip of the material, as the reference and as each method decoded it."""

    mip: int
    x: int  # left texel of the region within the mip
    y: int  # top texel
    size: int  # side in texels
    reference: np.ndarray  # (size, size, 8) float32 in [0, 1]: the 8 material channels (albedo rgb, normal xy, ARM)
    methods: dict[str, np.ndarray]  # label -> (size, size, 8) float32; "ours" first, then baselines by name

    def __post_init__(self) -> None:
        # Fail when the crop is made, not halfway through a page: a wrong shape is a caller's bug.
        expected = (self.size, self.size, 8)
        for label, image in {"reference": self.reference, **self.methods}.items():
            if tuple(np.shape(image)) != expected:
                raise ValueError(f"crop at mip {self.mip} ({self.x}, {self.y}): {label} has shape "
                                 f"{tuple(np.shape(image))}, expected {expected}")


class _Method(NamedTuple):
    """One row of the comparison: ours or a baseline, with what the summary table and charts need."""

    name: str
    description: str
    aggregate: Aggregate
    per_mip: list[MipMetrics]
    size_bytes: int
    bits_per_texel: float
    encode_s: float


# ------------------------------------------------------------------------------------------------ formatting


def _e(value: object) -> str:
    return html.escape(str(value), quote=True)


def _mib(size_bytes: float) -> str:
    return f"{size_bytes / MIB:.4g}"


def _seconds(seconds: float) -> str:
    return f"{seconds:.2f}" if seconds < 10 else f"{seconds:.1f}"


def _db(value: float) -> str:
    return f"{value:.2f}"


def _table(header: Sequence[str], rows: Iterable[Sequence[str]], classes: Optional[Sequence[str]] = None,
           numeric_from: int = 1) -> str:
    """An HTML table of already-escaped cells; columns from `numeric_from` on are right-aligned numbers."""
    head = "".join(f'<th{" class=num" if i >= numeric_from else ""}>{h}</th>' for i, h in enumerate(header))
    body = []
    for r, row in enumerate(rows):
        css = f' class="{classes[r]}"' if classes and classes[r] else ""
        cells = "".join(f'<td{" class=num" if i >= numeric_from else ""}>{c}</td>' for i, c in enumerate(row))
        body.append(f"<tr{css}>{cells}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


# ---------------------------------------------------------------------------------------------------- images


def _data_url(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _png(image: np.ndarray, cmap: Optional[str] = None, vmax: Optional[float] = None) -> bytes:
    """(h, w, 3) values in [0, 1], or (h, w) scalars with a colormap on [0, vmax], as PNG bytes."""
    buffer = io.BytesIO()
    if cmap is None:
        imsave(buffer, np.clip(image, 0.0, 1.0), format="png")
    else:
        imsave(buffer, image, format="png", cmap=cmap, vmin=0.0, vmax=vmax)
    return buffer.getvalue()


def _enlarge(image: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement in the file itself (the CSS asks for pixelated too), so blocks stay
    visible in viewers and print paths that ignore `image-rendering`."""
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def _img(png: bytes, alt: str, css: str = "", width: Optional[int] = None) -> str:
    size = f' width="{width}"' if width else ""
    cls = f' class="{css}"' if css else ""
    return f'<img src="{_data_url(png)}" alt="{_e(alt)}"{cls}{size}>'


def _figure_png(figure: Figure) -> bytes:
    if not isinstance(figure.canvas, FigureCanvasAgg):
        FigureCanvasAgg(figure)  # attaches itself to the figure: Agg rendering without pyplot
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=CHART_DPI, bbox_inches="tight")
    return buffer.getvalue()


# --------------------------------------------------------------------------------------------------- methods


def _methods(report: Report) -> list[_Method]:
    """Ours first, then the baselines in report order."""
    t = report.timing
    ours = _Method(OURS, "neural BC6H features + MLP decoder (this export)", report.aggregate, report.per_mip,
                   report.size.total_bytes, report.size.bits_per_texel,
                   t.phase1_s + t.transition_s + t.phase2_s + t.export_s)
    return [ours] + [_Method(name, b.description, b.aggregate, b.per_mip, b.size_bytes, b.bits_per_texel,
                             b.encode_s) for name, b in report.baselines.items()]


def _colours(methods: Sequence[_Method]) -> dict[str, str]:
    """Ours in a fixed red; baselines in tab10 order, skipping its red so nothing is confused with ours."""
    palette = [c for i, c in enumerate(colormaps["tab10"].colors) if i != 3]
    others = [m.name for m in methods if m.name != OURS]
    colours = {name: "#%02x%02x%02x" % tuple(int(round(255 * v)) for v in palette[i % len(palette)])
               for i, name in enumerate(others)}
    return {OURS: OURS_COLOUR, **colours}


# ---------------------------------------------------------------------------------------------------- charts


def _side(mip: MipMetrics) -> str:
    """A short size label: 12 mips of a 2K material must fit under one chart's axis."""
    return str(mip.width) if mip.width == mip.height else f"{mip.width}x{mip.height}"


def _per_mip_chart(methods: Sequence[_Method], colours: dict[str, str]) -> bytes:
    figure = Figure(figsize=(6.4, 4.0))
    ax = figure.add_subplot()
    for method in reversed(methods):  # ours drawn last, on top
        mips = [m.mip for m in method.per_mip]
        values = [m.psnr.all for m in method.per_mip]
        ours = method.name == OURS
        ax.plot(mips, values, marker="o", color=colours[method.name], label=method.name,
                linewidth=2.8 if ours else 1.3, markersize=6 if ours else 4, zorder=3 if ours else 2)
    ours = methods[0]
    ax.set_xticks([m.mip for m in ours.per_mip], [f"{m.mip}\n{_side(m)}" for m in ours.per_mip],
                  fontsize=8)
    ax.set_xlabel("mip level")
    ax.set_ylabel("PSNR, all channels (dB)")
    ax.set_title("PSNR per mip")
    ax.grid(True, alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    ax.legend(handles[::-1], labels[::-1], fontsize=8)  # legend in table order: ours first
    return _figure_png(figure)


Box = tuple[float, float, float, float]  # x0, y0, x1, y1 in display pixels

# Where a point's name may go, in points from the point, in order of preference (right, then left, then further
# above / below): the first that overlaps no other name or marker is used.
_LABEL_OFFSETS = ((6, 4), (6, -11), (-6, 4), (-6, -11), (6, 14), (6, -21), (-6, 14), (-6, -21), (6, 24), (6, -31))


def _size_chart(methods: Sequence[_Method], colours: dict[str, str], floor_db: float) -> bytes:
    figure = Figure(figsize=(6.4, 4.0))
    canvas = FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    points = {m.name: (m.size_bytes / MIB, m.aggregate.psnr.all) for m in methods}
    for method in methods:
        ours = method.name == OURS
        ax.scatter(*points[method.name], s=90 if ours else 40, color=colours[method.name], zorder=3 if ours else 2,
                   marker="*" if ours else "o")
    ax.axhline(floor_db, color="0.5", linestyle="--", linewidth=1)
    ax.annotate("per-channel mean (floor)", (0.01, floor_db), xycoords=("axes fraction", "data"),
                xytext=(0, 3), textcoords="offset points", fontsize=7, color="0.4")
    ax.set_xscale("log")
    # Labels at 1, 2, 5 x 10^k in plain decimals; the default labels every minor tick in 10^k notation there,
    # which overlap when the sizes span less than a decade.
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.margins(x=0.3, y=0.15)
    ax.set_xlabel("size in memory (MiB, log scale)")
    ax.set_ylabel("aggregate PSNR, all channels (dB)")
    ax.set_title("Quality against size")
    ax.grid(True, which="both", alpha=0.3)
    _place_labels(ax, canvas.get_renderer(), points, colours)
    return _figure_png(figure)


def _place_labels(ax: Axes, renderer: RendererBase, points: dict[str, tuple[float, float]],
                  colours: dict[str, str]) -> None:
    """Name every point, moving a name around its point until it covers no other name or marker and stays in
    the plot: codecs of similar size and quality otherwise print on top of each other. Ours is placed first,
    so it gets the best spot; a name that fits nowhere takes the first spot."""
    ax.autoscale_view()  # the data limits are final now, so pixel positions measured here hold when saved
    centres = {name: ax.transData.transform(xy) for name, xy in points.items()}
    markers = {name: (c[0] - 5.0, c[1] - 5.0, c[0] + 5.0, c[1] + 5.0) for name, c in centres.items()}
    frame = ax.get_window_extent(renderer)
    placed: list[Box] = []
    for name, xy in points.items():
        obstacles = placed + [box for other, box in markers.items() if other != name]
        for offset in _LABEL_OFFSETS:
            label, box = _label(ax, renderer, name, xy, offset, colours[name])
            inside = frame.x0 <= box[0] and box[2] <= frame.x1 and frame.y0 <= box[1] and box[3] <= frame.y1
            if inside and not any(_overlap(box, other) for other in obstacles):
                break
            label.remove()
        else:  # nowhere free: the preferred spot
            label, box = _label(ax, renderer, name, xy, _LABEL_OFFSETS[0], colours[name])
        placed.append(box)


def _label(ax: Axes, renderer: RendererBase, name: str, xy: tuple[float, float], offset: tuple[int, int],
           colour: str) -> tuple[Annotation, Box]:
    """A point's name at `offset` points from it (left of it for a negative x offset), and its pixel box."""
    label = ax.annotate(name, xy, xytext=offset, textcoords="offset points", fontsize=8, color=colour,
                        ha="left" if offset[0] > 0 else "right", fontweight="bold" if name == OURS else "normal")
    extent = label.get_window_extent(renderer)
    return label, (extent.x0, extent.y0, extent.x1, extent.y1)


def _overlap(a: Box, b: Box) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


# ----------------------------------------------------------------------------------------------------- parts


def _header(report: Report) -> str:
    o, m = report.options, report.material
    items = [
        ("Resolution", f"{m.width} x {m.height}"),
        ("Options", f"preset {o.preset}, features {o.features}, BC6H block mode {o.block_mode}, {o.init} start, "
                    f"hidden {o.hidden}, {o.phase1_iterations} + {o.phase2_iterations} iterations, "
                    f"batch {o.batch_size}, address {o.address}, seed {o.seed}"),
        ("Normal map", f"{m.normal_convention}, "
                       f"{'ARM packed' if m.arm_packed else 'separate AO / roughness / metalness'}"),
        ("Device", report.device),
        ("Created", report.created_at),
        ("Generator", report.generator),
    ]
    rows = "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in items)
    return f"<header><h1>{_e(m.name)}</h1><p class=sub>bcf compression report</p><dl>{rows}</dl></header>"


def _summary(report: Report, methods: Sequence[_Method]) -> str:
    ranked = sorted(methods, key=lambda m: m.size_bytes)
    rows = [[f"<b>{_e(m.name)}</b>" if m.name == OURS else _e(m.name), _e(m.description),
             _db(m.aggregate.psnr.all), _db(m.aggregate.psnr.albedo), _db(m.aggregate.psnr.normal),
             _db(m.aggregate.psnr.arm), f"{m.aggregate.ssim.all:.4f}", _mib(m.size_bytes),
             f"{m.bits_per_texel:.2f}", _seconds(m.encode_s)] for m in ranked]
    header = ["method", "description", "PSNR all", "PSNR albedo", "PSNR normal", "PSNR ARM", "SSIM all",
              "size (MiB)", "bits / texel", "encode (s)"]
    main = _table(header, rows, ["ours" if m.name == OURS else "" for m in ranked], numeric_from=2)

    points = [("ours, 1 spp jittered", "one random sample per texel against the filtered reference",
               report.jittered.aggregate)]
    points += [(f"model: {name}", _MODEL_NOTES.get(name, ""), a) for name, a in report.models.items()]
    points.append(("per-channel mean", "the material's mean everywhere: the floor any decoder must clear",
                   report.mean_baseline))
    extra = _table(["evaluation", "what it is", "PSNR all", "PSNR albedo", "PSNR normal", "PSNR ARM", "SSIM all"],
                   [[_e(n), _e(d), _db(a.psnr.all), _db(a.psnr.albedo), _db(a.psnr.normal), _db(a.psnr.arm),
                     f"{a.ssim.all:.4f}"] for n, d, a in points], numeric_from=2)
    return (f"<section><h2>Summary</h2><p>Aggregate scores over all mips (PSNR of the mean MSE, mean SSIM) at the "
            f"texel centres of every reference mip, on stored values in [0, 1]; sorted by size. Encode time for "
            f"ours is training plus export.</p>{main}"
            f"<h3>Other evaluations of ours</h3>{extra}</section>")


_MODEL_NOTES = {
    "exported": "decoded from the exported files (the numbers above)",
    "trained_fp32": "the trained model before export (fp32 weights)",
    "phase1_unconstrained": "after phase 1, features not yet BC6H blocks",
}


def _charts(report: Report, methods: Sequence[_Method], colours: dict[str, str]) -> str:
    per_mip = _img(_per_mip_chart(methods, colours), "PSNR per mip, one line per method", "chart")
    size = _img(_size_chart(methods, colours, report.mean_baseline.psnr.all), "PSNR against size", "chart")
    return f"<section><h2>Charts</h2><div class=charts>{per_mip}{size}</div></section>"


def _per_mip_table(methods: Sequence[_Method]) -> str:
    mips = methods[0].per_mip
    scores = [{m.mip: m.psnr.all for m in method.per_mip} for method in methods]
    rows = [[str(m.mip), f"{m.width} x {m.height}"]
            + [_db(s[m.mip]) if m.mip in s else "&ndash;" for s in scores] for m in mips]
    header = ["mip", "size"] + [f"<b>{_e(m.name)}</b>" if m.name == OURS else _e(m.name) for m in methods]
    return (f"<section><h2>PSNR per mip (all channels, dB)</h2>"
            f"{_table(header, rows, numeric_from=2)}</section>")


def _texture_error(reference: np.ndarray, test: np.ndarray, channels: slice) -> tuple[np.ndarray, float]:
    """Per-texel mean absolute error over one texture's channels, and that texture's PSNR on the crop."""
    difference = np.clip(test[..., channels], 0.0, 1.0).astype(np.float64) - reference[..., channels]
    return np.abs(difference).mean(axis=-1), psnr_from_mse(float(np.mean(difference**2)))


def _legend() -> str:
    ramp = np.tile(np.linspace(0.0, ERROR_MAX, 256), (12, 1))
    return (f'<div class=legend>error maps: mean absolute error over the texture\'s stored channels, '
            f'<span>0</span>{_img(_png(ramp, ERROR_CMAP, ERROR_MAX), "error colour scale", "ramp")}'
            f'<span>&ge; {ERROR_MAX:g}</span> (same scale for every method)</div>')


def _crop(crop: Crop, mip_size: Optional[tuple[int, int]]) -> str:
    factor = max(2, -(-CROP_DISPLAY_PX // crop.size))  # at least 2x: 4x4 blocks must stand out even in big crops
    shown = crop.size * factor
    reference = np.clip(np.asarray(crop.reference, dtype=np.float32), 0.0, 1.0)
    originals = material_images(reference)
    decoded_images = {label: material_images(np.asarray(image, dtype=np.float32))
                      for label, image in crop.methods.items()}
    header = "<th></th><th>reference</th>" + "".join(f"<th>{_e(label)}</th>" for label in crop.methods)
    rows = []
    for texture, channels in TEXTURES.items():
        cells = [f'<th class=rowhead>{_e(TEXTURE_TITLES[texture])}</th>',
                 f"<td>{_img(_png(_enlarge(originals[texture], factor)), f'reference {texture}', 'px', shown)}</td>"]
        for label, image in crop.methods.items():
            error, psnr = _texture_error(reference, np.asarray(image, dtype=np.float32), channels)
            decoded = _img(_png(_enlarge(decoded_images[label][texture], factor)), f"{label} {texture}", "px", shown)
            heat = _img(_png(_enlarge(error, factor), ERROR_CMAP, ERROR_MAX), f"{label} {texture} error", "px",
                        shown)
            cells.append(f"<td>{decoded}{heat}<div class=psnr>{_db(psnr)} dB</div></td>")
        rows.append(f"<tr>{''.join(cells)}</tr>")
    where = f" of {mip_size[0]} x {mip_size[1]}" if mip_size else ""
    title = (f"mip {crop.mip}{where}: texels x {crop.x}&ndash;{crop.x + crop.size - 1}, "
             f"y {crop.y}&ndash;{crop.y + crop.size - 1} ({crop.size} x {crop.size}, shown {factor}x)")
    return (f"<figure class=crop><figcaption>{title}</figcaption><div class=scroll><table class=grid>"
            f"<thead><tr>{header}</tr></thead><tbody>{''.join(rows)}</tbody></table></div></figure>")


def _detail_window(mip: torch.Tensor, size: int) -> tuple[int, int]:
    """(x, y) of the size x size window, on a grid of half-overlapping windows, with the most variance
    over the 8 channels: crops should show detail, not a flat patch."""
    _, h, w = mip.shape
    step = max(1, size // 2)
    best, where = -1.0, (0, 0)
    for y in range(0, h - size + 1, step):  # a few dozen windows at most
        row = mip[:, y:y + size].unfold(2, size, step)  # (C, size, windows, size)
        variance = row.var(dim=(1, 3)).sum(0)
        index = int(torch.argmax(variance))
        if float(variance[index]) > best:
            best, where = float(variance[index]), (index * step, y)
    return where


def select_crops(reference: ReferenceMaterial, decoders: dict[str, DecoderFunction]) -> list[Crop]:
    """Crops of mip 0 and the middle mip for the page: the reference and, of `decoders`, ours and
    `CROP_BASELINES`, at the texel centres of the most detailed window."""
    decoders = {k: v for k, v in decoders.items() if k == OURS or k in CROP_BASELINES}
    crops = []
    for level, side in zip((0, reference.levels // 2), CROP_TEXELS):
        mip = reference.mip(level)
        _, h, w = mip.shape
        size = min(side, w, h)
        x, y = _detail_window(mip, size)
        methods = {name: render_region(decoder, w, h, float(level), x, y, size).clamp(0.0, 1.0)
                   .permute(1, 2, 0).numpy() for name, decoder in decoders.items()}
        crops.append(Crop(mip=level, x=x, y=y, size=size,
                          reference=mip[:, y:y + size, x:x + size].permute(1, 2, 0).numpy(),
                          methods=methods))
    return crops


def _crops(report: Report, crops: Sequence[Crop]) -> str:
    if not crops:
        return ""
    sizes = {m.mip: (m.width, m.height) for m in report.per_mip}
    body = "".join(_crop(c, sizes.get(c.mip)) for c in crops)
    return (f"<section><h2>Crops</h2><p>Decoded texels next to the reference mip; beneath each: the error map "
            f"and the PSNR of that texture on this crop. Normal z is rebuilt from x and y for display."
            f"</p>{_legend()}{body}</section>")


def _sizes_and_times(report: Report) -> str:
    s, t = report.size, report.timing
    sizes = [["features (BC6H blocks, all mips)", f"{s.features_bytes:,}", _mib(s.features_bytes)],
             ["decoder weights", f"{s.weights_bytes:,}", _mib(s.weights_bytes)],
             ["<b>total in memory</b>", f"<b>{s.total_bytes:,}</b>", f"<b>{_mib(s.total_bytes)}</b>"],
             ["files on disk (with manifest and report)", f"{s.files_bytes:,}", _mib(s.files_bytes)],
             ["BC1 + BC5 with full mips, for comparison", f"{s.bc1_bc5_bytes:,}", _mib(s.bc1_bc5_bytes)]]
    sizes += [[f"baseline {_e(name)}", f"{b.size_bytes:,}", _mib(b.size_bytes)] for name, b in report.baselines.items()]
    size_table = _table(["what", "bytes", "MiB"], sizes)
    times = [["start and phase 1 (unconstrained features)", _seconds(t.phase1_s)],
             ["transition (block fit)", _seconds(t.transition_s)],
             ["phase 2 (BC6H block features)" + (", ended below its start: the export holds the start"
                                                  if report.start_kept else ""), _seconds(t.phase2_s)],
             ["export", _seconds(t.export_s)], ["evaluation", _seconds(t.evaluation_s)],
             ["<b>total</b>", f"<b>{_seconds(t.total_s)}</b>"]]
    time_table = _table(["ours", "seconds"], times)
    parts = [f"<h3>Sizes</h3><p>{s.bits_per_texel:.2f} bits per texel for ours.</p>{size_table}",
             f"<h3>Timings</h3><p>On {_e(report.device)}.</p>{time_table}"]
    if report.baselines:
        rows = [[_e(name), _e(b.encoder), f"{b.width} x {b.height}", _seconds(b.encode_s), _seconds(b.evaluation_s)]
                for name, b in report.baselines.items()]
        parts.append("<h3>Baselines</h3>"
                     + _table(["baseline", "encoder", "top mip", "encode (s)", "evaluation (s)"], rows, numeric_from=2))
    return f"<section><h2>Sizes and timings</h2>{''.join(parts)}</section>"


_STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif;
       color: #1d1d1f; background: #fff; margin: 0 auto; padding: 24px 32px 48px; max-width: 1280px;
       font-size: 14px; line-height: 1.45; }
h1 { font-size: 26px; margin: 0; }
h2 { font-size: 19px; margin: 32px 0 8px; padding-bottom: 4px; border-bottom: 1px solid #d0d0d5; }
h3 { font-size: 15px; margin: 20px 0 6px; }
p.sub { margin: 2px 0 12px; color: #666; }
dl { display: grid; grid-template-columns: max-content 1fr; gap: 2px 16px; margin: 0; }
dt { color: #666; } dd { margin: 0; }
table { border-collapse: collapse; margin: 6px 0; }
th, td { padding: 4px 10px; border-bottom: 1px solid #e4e4e8; text-align: left; vertical-align: top; }
thead th { background: #f4f4f6; font-weight: 600; }
.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.ours td { background: #fdecea; }
.charts { display: flex; flex-wrap: wrap; gap: 16px; }
img.chart { max-width: 100%; height: auto; border: 1px solid #e4e4e8; }
img.px { image-rendering: pixelated; display: block; height: auto; }
img.px + img.px { margin-top: 4px; }
.scroll { overflow-x: auto; }
table.grid td, table.grid th { border: none; padding: 4px 6px; text-align: center; }
table.grid th.rowhead { text-align: right; vertical-align: middle; font-weight: 600; max-width: 110px;
                        position: sticky; left: 0; background: #fff; z-index: 1; }
.psnr { font-size: 12px; color: #333; font-variant-numeric: tabular-nums; }
figure.crop { margin: 16px 0 24px; }
figcaption { font-weight: 600; margin-bottom: 4px; }
.legend { font-size: 12px; color: #444; display: flex; align-items: center; gap: 6px; flex-wrap: wrap; }
img.ramp { width: 200px; height: 12px; image-rendering: pixelated; border: 1px solid #ccc; }
footer { margin-top: 40px; color: #777; font-size: 12px; }
"""


# ---------------------------------------------------------------------------------------------------- public


def render_html_report(report: Report, crops: Sequence[Crop]) -> str:
    """The whole report.html page as a string: header, summary, charts, per-mip table, crops, sizes, times."""
    methods = _methods(report)
    colours = _colours(methods)
    body = "".join([_header(report), _summary(report, methods), _charts(report, methods, colours),
                    _per_mip_table(methods), _crops(report, crops), _sizes_and_times(report),
                    f"<footer>Generated by {_e(report.generator)} on {_e(report.created_at)}.</footer>"])
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{_e(report.material.name)} &ndash; bcf report</title><style>{_STYLE}</style></head>"
            f"<body>{body}</body></html>\n")


def write_html_report(path: Path, report: Report, crops: Sequence[Crop]) -> None:
    """Render and write the page atomically (`write_text_atomic`): a reader never sees half a page and a failure
    leaves any previous page as it was."""
    page = render_html_report(report, crops)  # before touching the disk: a rendering error writes nothing
    write_text_atomic(Path(path), page)
