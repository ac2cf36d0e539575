"""Fast unit tests for the numerics of the neural material: sampling, pyramid geometry, the decoder's
folding, the phase 1 -> 2 transition, metrics and options."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bcf.core.codec import bc6h
from bcf.core.fit import pca, training
from bcf.core.report import metrics
from bcf.core.fit import model
from bcf.core.report import report_json as report
from bcf.core.options import (MAX_BATCH, MAX_ITERATIONS, MAX_LEARNING_RATE, MAX_SEED, PRESETS, CompressOptions,
                              ResolvedOptions, resolve_options)
from bcf.core.export.decode import render_mip
from bcf.core.fit.batches import BatchSampler
from bcf.core.fit.sampling import (ReferenceMaterial, material_mip_count, sample_bicubic, sample_bilinear,
                                   sample_trilinear, texel_centres, trilinear_levels, wrap_pad)


def _bilinear_reference(image: np.ndarray, u: float, v: float, wrap: bool) -> np.ndarray:
    """Textbook bilinear lookup with texel centres at (i + 0.5) / n, written independently of grid_sample."""
    c, h, w = image.shape
    x, y = u * w - 0.5, v * h - 0.5
    x0, y0 = math.floor(x), math.floor(y)
    ax, ay = x - x0, y - y0

    def tap(i: int, j: int) -> np.ndarray:
        i = i % w if wrap else min(max(i, 0), w - 1)
        j = j % h if wrap else min(max(j, 0), h - 1)
        return image[:, j, i]

    return ((1 - ax) * (1 - ay) * tap(x0, y0) + ax * (1 - ay) * tap(x0 + 1, y0)
            + (1 - ax) * ay * tap(x0, y0 + 1) + ax * ay * tap(x0 + 1, y0 + 1))


@pytest.mark.parametrize("address", ["wrap", "clamp"])
def test_bilinear_matches_textbook_filter(address: str) -> None:
    rng = np.random.default_rng(1)
    image = rng.random((3, 8, 16)).astype(np.float32)
    uv = np.concatenate([rng.random((200, 2)), [[0.0, 0.0], [0.999, 0.999], [0.5 / 16, 0.5 / 8]]])
    if address == "wrap":
        uv = np.concatenate([uv, uv[:20] + 1.0, uv[:20] - 2.0])  # periodic
    got = sample_bilinear(torch.from_numpy(image), torch.from_numpy(uv).float(), address).numpy()
    want = np.stack([_bilinear_reference(image, u, v, address == "wrap") for u, v in uv])
    np.testing.assert_allclose(got, want, atol=2e-6)


def test_bilinear_at_texel_centres_returns_texels() -> None:
    image = torch.rand(3, 8, 4)
    values = sample_bilinear(image, texel_centres(4, 8), "wrap")
    torch.testing.assert_close(values.T.reshape(3, 8, 4), image)


def test_bicubic_reproduces_constants_and_is_periodic_with_wrap() -> None:
    image = torch.full((2, 8, 8), 0.25)
    uv = torch.rand(100, 2)
    torch.testing.assert_close(sample_bicubic(image, uv, "wrap"), torch.full((100, 2), 0.25))
    ramp = torch.rand(1, 8, 8)
    torch.testing.assert_close(sample_bicubic(ramp, uv, "wrap"), sample_bicubic(ramp, uv + 3.0, "wrap"),
                               atol=1e-5, rtol=0)


def test_trilinear_levels_clamp_and_blend() -> None:
    assert trilinear_levels(-1.0, 5) == (0, 1, 0.0)  # magnification: level 0 alone
    assert trilinear_levels(1.25, 5) == (1, 2, 0.25)
    assert trilinear_levels(4.0, 5) == (4, 4, 0.0)
    assert trilinear_levels(9.0, 5) == (4, 4, 0.0)
    levels = [torch.full((1, 8 >> l, 8 >> l), float(l)) for l in range(3)]
    uv = torch.rand(10, 2)
    value = sample_trilinear(lambda l: levels[l], 3, uv, 1.5, "wrap")
    torch.testing.assert_close(value, torch.full((10, 1), 1.5))


def test_reference_pyramid_and_scale_range() -> None:
    channels = np.random.default_rng(0).random((64, 128, 8)).astype(np.float32)
    reference = ReferenceMaterial(channels, "wrap")
    assert material_mip_count(128, 64) == 5 == reference.levels
    assert [tuple(m.shape) for m in reference.mips][-1] == (8, 4, 8)  # shorter side 4
    # The box filter preserves the mean; bicubic at texel centres of a level returns its texels.
    np.testing.assert_allclose(reference.mip(2).mean((1, 2)).numpy(), channels.mean((0, 1)), atol=1e-5)
    torch.testing.assert_close(reference.sample(texel_centres(32, 16), 2.0).T.reshape(8, 16, 32), reference.mip(2),
                               atol=1e-5, rtol=0)


@pytest.mark.parametrize("size", [(4, 4, 1), (8, 16, 2), (5, 7, 2), (4, 4, 4)], ids=str)
def test_wrap_pad_matches_circular_pad_values_and_gradients(size: tuple[int, int, int]) -> None:
    h, w, pad = size
    image = torch.randn(3, h, w, dtype=torch.float64, requires_grad=True)
    upstream = torch.randn(1, 3, h + 2 * pad, w + 2 * pad, dtype=torch.float64)
    ours = wrap_pad(image, pad)
    (ours * upstream).sum().backward()
    ours_grad, image.grad = image.grad, None
    torch_pad = torch.nn.functional.pad(image.unsqueeze(0), (pad,) * 4, mode="circular")
    (torch_pad * upstream).sum().backward()
    assert torch.equal(ours, torch_pad)
    torch.testing.assert_close(ours_grad, image.grad)


def test_texel_batches_are_lookups_of_the_reference_at_texel_centres() -> None:
    """A texel step's targets are F(M) at its points (bicubic interpolates at texel centres); mips no larger
    than the batch come whole, every texel once, and every mip is drawn."""
    channels = np.random.default_rng(5).random((64, 32, 8)).astype(np.float32)
    reference = ReferenceMaterial(channels, "wrap")  # mips 32x64 .. 4x8
    generator = torch.Generator().manual_seed(0)
    sampler = BatchSampler(reference, 256, 0.0, 1.0, generator, generator)
    seen = set()
    for _ in range(60):
        batch = sampler()
        level = int(batch.s)
        assert batch.s == level
        seen.add(level)
        h, w = reference.mip(level).shape[1:]
        torch.testing.assert_close(batch.target, reference.sample(batch.uv, batch.s), atol=1e-5, rtol=0)
        texel = torch.floor(batch.uv * torch.tensor([w, h]))
        torch.testing.assert_close(batch.uv, (texel + 0.5) / torch.tensor([w, h]))  # texel centres
        if w * h <= 256:
            assert len(batch.uv) == w * h and len({tuple(t) for t in texel.tolist()}) == w * h  # dense
        else:
            assert len(batch.uv) == 256
    assert seen == set(range(reference.levels))


def test_continuous_only_batches_draw_as_the_papers_sampling() -> None:
    """continuous_fraction 1: s uniform over [0, S - 1] then uv uniform, from the same generator, as before
    texel steps existed (so such fits are unchanged)."""
    channels = np.random.default_rng(6).random((32, 32, 8)).astype(np.float32)
    reference = ReferenceMaterial(channels, "clamp")
    sampler = BatchSampler(reference, 300, 1.0, 1.0, torch.Generator().manual_seed(3),
                           torch.Generator().manual_seed(4))
    scales, points = torch.Generator().manual_seed(4), torch.Generator().manual_seed(3)
    for _ in range(3):
        batch = sampler()
        assert batch.s == float(torch.rand((), generator=scales)) * (reference.levels - 1)
        assert torch.equal(batch.uv, torch.rand((300, 2), generator=points))
        torch.testing.assert_close(batch.target, reference.sample(batch.uv, batch.s))


def test_jittered_mip_batches_sample_inside_the_texels_of_one_mip() -> None:
    channels = np.random.default_rng(8).random((64, 64, 8)).astype(np.float32)
    reference = ReferenceMaterial(channels, "wrap")
    generator = torch.Generator().manual_seed(2)
    sampler = BatchSampler(reference, 1024, 0.0, 0.0, generator, generator)
    for _ in range(20):
        batch = sampler()
        h, w = reference.mip(int(batch.s)).shape[1:]
        assert batch.s == int(batch.s) and len(batch.uv) == min(w * h, 1024)
        offsets = batch.uv * torch.tensor([w, h]) % 1.0
        assert float(offsets.std()) > 0.2  # spread over the texels, not at their centres (0.5)
        torch.testing.assert_close(batch.target, reference.sample(batch.uv, batch.s))


def test_mixed_batches_follow_the_continuous_fraction() -> None:
    channels = np.random.default_rng(7).random((32, 32, 8)).astype(np.float32)
    generator = torch.Generator().manual_seed(1)
    sampler = BatchSampler(ReferenceMaterial(channels, "wrap"), 512, 0.25, 0.0, generator, generator)
    continuous = sum(sampler().s % 1.0 != 0.0 for _ in range(400))
    assert 70 <= continuous <= 130  # 100 expected; an integer s from a continuous step has probability 0


def test_feature_textures_follow_table_1() -> None:
    # Paper Table 1 (2K material): T0..T3 sizes and mip counts for 0.5k / 1k / 2k.
    table = {"0.5k": [(512, 8), (256, 7), (128, 6), (64, 5)], "1k": [(1024, 9), (512, 8), (256, 7), (128, 6)],
             "2k": [(2048, 10), (1024, 9), (512, 8), (256, 7)]}
    for features, expected in table.items():
        specs = model.feature_textures(2048, 2048, features)
        assert [(s.width, s.levels) for s in specs] == expected
        assert [s.lod_bias for s in specs] == [math.log2(w / 2048) for w, _ in expected]
    small = model.feature_textures(64, 64, "0.5k")  # sides never below one block
    assert [(s.width, s.height, s.levels) for s in small] == [(16, 16, 3), (8, 8, 2), (4, 4, 1), (4, 4, 1)]
    wide = model.feature_textures(1024, 512, "1k")
    assert (wide[0].width, wide[0].height, wide[0].lod_bias) == (512, 256, -1.0)


def test_decoder_folding_is_exact() -> None:
    torch.manual_seed(0)
    decoder = model.Decoder(16)
    with torch.no_grad():
        decoder.input_scale.uniform_(0.5, 2.0)
        decoder.input_offset.uniform_(-1.0, 1.0)
    folded = model.Decoder.from_layers(decoder.folded_layers())
    x = torch.rand(50, 12)
    torch.testing.assert_close(folded(x), decoder(x), atol=1e-5, rtol=1e-5)


def test_transition_keeps_the_mlp_inputs() -> None:
    """Phase 1 -> 2 remaps feature values into [0, 1] and folds the inverse into the decoder, so before any
    phase-2 step the MLP sees nearly the phase-1 inputs (up to BC6H compression of the features)."""
    specs = model.feature_textures(64, 64, "2k")
    free = model.FreeFeatures(specs, torch.Generator().manual_seed(0))
    with torch.no_grad():
        for p in free.texels:  # smooth, range-shifted features compress well
            h, w = p.shape[1:]
            yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
            p.copy_(torch.stack([3 * xx - 1, 2 * yy + 5, xx * yy]))
    decoder = model.Decoder(16)
    phase1 = model.NeuralMaterial(free, decoder, "wrap")
    uv = torch.rand(500, 2)
    before = (phase1.sample_features(uv, 0.0) * decoder.input_scale + decoder.input_offset).detach()
    blocks = model.to_block_features(free, decoder, 10)
    phase2 = model.NeuralMaterial(blocks, decoder, "wrap")
    after = (phase2.sample_features(uv, 0.0) * decoder.input_scale + decoder.input_offset).detach()
    span = before.max(0).values - before.min(0).values
    assert float(((after - before).abs() / span.clamp(min=1e-3)).mean()) < 0.05
    stored = phase2.sample_features(uv, 0.0).detach()
    assert float(stored.min()) >= 0.0 and float(stored.max()) <= 1.3  # [0, 1] up to endpoint rounding


def test_block_features_export_the_blocks_they_decode() -> None:
    specs = model.feature_textures(64, 64, "1k")
    free = model.FreeFeatures(specs, torch.Generator().manual_seed(3))
    for mode in (10, 11, "auto"):
        blocks = model.to_block_features(free, model.Decoder(16), mode)
        for texture, spec in enumerate(specs):
            for level in range(spec.levels):
                w, h = spec.level_size(level)
                decoded = bc6h.decode_image(blocks.blocks(texture, level), w, h, signed=False)
                trained = blocks.level(texture, level).detach().numpy().transpose(1, 2, 0)
                np.testing.assert_array_equal(decoded.astype(np.float32), trained)


def test_auto_blocks_use_several_modes_and_fit_better() -> None:
    """With block_mode auto each block takes its best mode: on smooth features several modes are used, and the
    decoded features are closer to the free ones than with mode 11 alone."""
    specs = model.feature_textures(64, 64, "2k")
    free = model.FreeFeatures(specs, torch.Generator().manual_seed(4))
    with torch.no_grad():
        for p in free.texels:
            h, w = p.shape[1:]
            yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
            p.copy_(torch.stack([torch.sin(9 * xx) * yy, (xx > 0.5).float() + 0.2 * yy, xx * yy]) + 0.05 * p)
    errors = {}
    for mode in (11, "auto"):
        decoder = model.Decoder(16)
        blocks = model.to_block_features(free, decoder, mode)
        stored = model.NeuralMaterial(blocks, decoder, "wrap")
        before = model.NeuralMaterial(free, model.Decoder(16), "wrap")
        uv = torch.rand(2000, 2, generator=torch.Generator().manual_seed(5))
        mapped = stored.sample_features(uv, 0.0) * decoder.input_scale + decoder.input_offset
        errors[mode] = float(((mapped - before.sample_features(uv, 0.0)) ** 2).mean().detach())
        if mode == "auto":
            used = np.unique(np.concatenate([blocks.block_modes(0, level).ravel() for level in range(specs[0].levels)]))
            assert len(used) >= 3, used
    assert errors["auto"] < 0.7 * errors[11], errors


def test_pca_start_reproduces_the_coarser_mips_exactly() -> None:
    """Before any training, the principal-component start reproduces every material mip at least as coarse as
    the pyramids holding its components (mip 3 and up with 1k features: T2 holds components 6-7 at W/8), at
    texel centres, to float rounding; and it is far better than the material's mean at mip 0."""
    coarse = torch.rand(1, 8, 16, 16, generator=torch.Generator().manual_seed(6))
    smooth = torch.nn.functional.interpolate(coarse, size=(64, 64), mode="bilinear", align_corners=False)
    channels = smooth[0].permute(1, 2, 0).numpy().copy()
    channels[..., 3:5] = channels[..., :2] * 0.5 + 0.2  # correlated channels, as in real materials
    reference = ReferenceMaterial(channels, "wrap")
    specs = model.feature_textures(64, 64, "1k")
    torch.manual_seed(0)
    free, decoder = pca.pca_start(reference, specs, 16, torch.Generator().manual_seed(0))
    neural = model.NeuralMaterial(free, decoder, "wrap").eval()
    scores = metrics.evaluate(neural, reference)
    assert all(mip["psnr"]["all"] > 90.0 for mip in scores[3:]), [mip["psnr"]["all"] for mip in scores]
    assert scores[0]["psnr"]["all"] > metrics.mean_baseline(reference)[0]["psnr"]["all"] + 3.0


def test_ssim_and_psnr() -> None:
    image = torch.rand(3, 32, 32)
    assert metrics.ssim(image, image) == pytest.approx(1.0, abs=1e-6)
    assert metrics.ssim(image, torch.rand(3, 32, 32)) < 0.2
    assert metrics.ssim(image[:, :4, :4], image[:, :4, :4]) == pytest.approx(1.0, abs=1e-6)  # tiny mips work
    assert metrics.psnr_from_mse(0.01) == pytest.approx(20.0)
    assert metrics.psnr_from_mse(0.0) == 100.0


def test_scores_of_several_decoders_match_scoring_each_from_its_definition() -> None:
    """evaluate_at_centres (one pass over the mips, group scores as means over channels) gives, for
    every decoder and mip, the MSE, PSNR and SSIM computed straight from their definitions on each group's
    channels; the mean baseline predicts the per-channel mean of mip 0."""
    channels = np.random.default_rng(14).random((48, 32, 8)).astype(np.float32)
    reference = ReferenceMaterial(channels, "wrap")

    def wavy(uv: torch.Tensor, s: float) -> torch.Tensor:
        return 0.5 + 0.4 * torch.sin(torch.arange(1, 9) * (uv[:, :1] * 7 + uv[:, 1:] * 3 + s))

    def noisy(uv: torch.Tensor, s: float) -> torch.Tensor:
        return reference.sample(uv, s) + 0.05 * torch.cos(uv[:, :1] * 91 + torch.arange(8))

    scored = metrics.evaluate_at_centres({"wavy": wavy, "noisy": noisy}, reference, mean_baseline=True)
    mean = reference.mip(0).mean(dim=(1, 2), keepdim=True)
    for level in range(reference.levels):
        target = reference.mip(level)
        _, h, w = target.shape
        tests = {"wavy": render_mip(wavy, w, h, float(level)).clamp(0, 1),
                 "noisy": render_mip(noisy, w, h, float(level)).clamp(0, 1), "mean": mean.expand_as(target)}
        for name, test in tests.items():
            got = scored[name][level]
            for group, part in metrics.GROUPS.items():
                mse = float(torch.mean((target[part] - test[part]) ** 2))
                assert got["mse"][group] == pytest.approx(mse, rel=1e-5)
                assert got["psnr"][group] == pytest.approx(metrics.psnr_from_mse(mse), abs=1e-4)
                assert got["ssim"][group] == pytest.approx(metrics.ssim(target[part], test[part]), abs=1e-6)
    assert metrics.evaluate(noisy, reference) == scored["noisy"]
    assert metrics.mean_baseline(reference) == scored["mean"]


def test_summary_aggregates_mse_over_mips() -> None:
    mips = [{"mse": {k: m for k in ("albedo", "normal", "arm", "all")},
             "psnr": {k: metrics.psnr_from_mse(m) for k in ("albedo", "normal", "arm", "all")},
             "ssim": {k: s for k in ("albedo", "normal", "arm", "all")}} for m, s in ((0.01, 0.5), (0.0001, 0.9))]
    summary = report.summarise(mips, [(8, 8), (4, 4)])
    assert summary.aggregate.psnr.all == pytest.approx(-10 * math.log10(0.00505))
    assert summary.aggregate.ssim.all == pytest.approx(0.7)
    assert [m.mip for m in summary.per_mip] == [0, 1]


def test_bc1_bc5_size() -> None:
    # 2048^2: BC1 + BC1 + BC5 = 32 bytes per 4x4 block over the full chain (the paper's "BC 2048" 10.67 MB).
    assert report.bc1_bc5_bytes(2048, 2048) == 32 * sum(max(1, (2048 >> l) // 4) ** 2 for l in range(12))
    assert report.bc1_bc5_bytes(2048, 2048) / 2**20 == pytest.approx(10.67, abs=0.01)


def test_presets_resolve_with_overrides() -> None:
    paper = resolve_options(CompressOptions(preset="paper"))
    assert (paper.phase1_iterations, paper.phase2_iterations, paper.batch_size) == (5000, 200_000, 512 * 512)
    assert (paper.lr_features_phase1, paper.lr_mlp_phase1, paper.decay_phase1) == (5e-2, 1e-3, 0.9995)
    assert (paper.lr_features_phase2, paper.lr_mlp_phase2, paper.decay_phase2) == (1e-2, 1e-3, 0.99999)
    assert (paper.hidden, paper.block_mode) == (16, 10)
    assert (paper.continuous_fraction, paper.centre_fraction) == (1.0, 1.0)  # the paper's sampling
    # Manifests and reports written before the sampling options existed still read, as the paper's sampling.
    earlier = resolve_options(CompressOptions()).model_dump(exclude={"continuous_fraction", "centre_fraction"})
    assert ResolvedOptions(**earlier).continuous_fraction == ResolvedOptions(**earlier).centre_fraction == 1.0
    custom = resolve_options(CompressOptions(preset="fast", phase2_iterations=7, hidden=32))
    assert custom.phase2_iterations == 7 and custom.hidden == 32
    assert custom.phase1_iterations == PRESETS["fast"].phase1_iterations
    for preset in PRESETS.values():  # exponential schedules end near the paper's final learning-rate ratios
        if preset.schedule == "exponential":
            assert preset.decay_phase1 ** preset.phase1_iterations == pytest.approx(0.082, rel=0.1)
            assert preset.decay_phase2 ** preset.phase2_iterations == pytest.approx(0.135, rel=0.1)
        else:  # cosine ones at 0, whatever the iteration count
            for iterations in (300, 2000):
                assert training.learning_rate_factor("cosine", 1.0, 0, iterations) == 1.0
                assert training.learning_rate_factor("cosine", 1.0, iterations, iterations) == pytest.approx(
                    0.0, abs=1e-12)
    assert (PRESETS["default"].init, PRESETS["default"].block_mode) == ("pca", "auto")
    assert PRESETS["fast"].phase2_iterations == 0  # the start alone
    # Manifests written before the start, schedule and endpoint rate existed read as the paper's fit.
    older = resolve_options(CompressOptions(preset="paper")).model_dump(exclude={"init", "schedule",
                                                                                 "lr_endpoints_phase2"})
    assert (ResolvedOptions(**older).init, ResolvedOptions(**older).schedule) == ("random", "exponential")
    assert ResolvedOptions(**older).lr_endpoints_phase2 is None
    with pytest.raises(ValueError):
        CompressOptions(preset="fast", unknown=1)
    for preset in ("default", "fast"):  # a random start needs phase 1, with or without phase 2
        with pytest.raises(ValueError, match="phase-1 iterations"):
            CompressOptions(preset=preset, init="random")
    assert resolve_options(CompressOptions(preset="default", init="random", phase1_iterations=100)).init == "random"
    assert CompressOptions(block_mode="10").block_mode == 10  # a command line's string


@pytest.mark.parametrize("field, value", [("seed", 2**64), ("seed", -1), ("phase2_iterations", 10**12),
                                          ("phase1_iterations", 10**12), ("batch_size", 10**9),
                                          ("lr_features_phase2", 1e30), ("lr_mlp_phase1", 2.0),
                                          ("lr_endpoints_phase2", float("inf")), ("lr_features_phase1", float("nan"))])
def test_options_beyond_any_useful_value_are_refused(field: str, value: object) -> None:
    """What a remote client sends is bounded before a fit starts: no overflow, no runaway memory or time."""
    with pytest.raises(ValueError, match=field):
        CompressOptions(**{field: value})
    limits = CompressOptions(seed=MAX_SEED, phase2_iterations=MAX_ITERATIONS, batch_size=MAX_BATCH,
                             lr_features_phase2=MAX_LEARNING_RATE)  # the bounds themselves are allowed
    assert limits.seed == MAX_SEED
