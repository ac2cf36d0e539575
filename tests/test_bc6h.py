"""Tests of bcf.core.bc6h: the decoder against two independent decoders (Mesa's OpenGL and OpenImageIO),
the mode-10/11 encoder with its anchor rule, the differentiable decode's bit-exact forward pass, and the
partition search."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from bcf.core.codec import bc6h
from bcf.core.codec import partition as bc6h_partition
from bcf.core.fit import block_decode
from bcf.core.codec.containers import BC6HTexture, full_mip_count, mip_size, read_dds, write_dds
from bcf.core.codec.textures import psnr
from bcf.core.material.images import mip_chain, read_rgb
from reference_decoders import MesaBC6HDecoder, decode_with_mesa, decode_with_oiio

NEGATIVE_ZERO = 0x8000
SAMPLE_ALBEDO = Path(__file__).resolve().parents[1] / "examples" / "sample" / "albedo.png"  # real, CC0, 256x256


def random_blocks(rng: np.random.Generator, shape: tuple[int, ...], spec: bc6h.ModeSpec | None) -> np.ndarray:
    """Random 16-byte blocks whose mode field is `spec`'s (or a reserved code when spec is None)."""
    blocks = rng.integers(0, 256, (*shape, 16), dtype=np.uint8)
    if spec is None:
        codes = np.array(bc6h.RESERVED_CODES, dtype=np.uint8)[rng.integers(0, 4, shape)]
        blocks[..., 0] = (blocks[..., 0] & 0xE0) | codes
    else:
        keep = 0xFF ^ ((1 << spec.code_bits) - 1)
        blocks[..., 0] = (blocks[..., 0] & keep) | spec.code
    return blocks


def expected_half_bits(endpoints: np.ndarray, index: np.ndarray, subset: np.ndarray, bits: int,
                       signed: bool) -> np.ndarray:
    """What explicit-endpoint parameters mean, straight from the format's definition (no block packing):
    endpoints (n, R, 2, 3), index (n, 16) into the 3- or 4-bit weight table, subset (n, 16)."""
    table = bc6h.WEIGHTS_3BIT if endpoints.shape[1] == 2 else bc6h.WEIGHTS_4BIT
    unq = bc6h.unquantize(endpoints.astype(np.int64), bits, signed)
    rows = np.arange(len(index))[:, None]
    c = bc6h.interpolate(unq[rows, subset, 0], unq[rows, subset, 1], table[index][..., None])
    return bc6h.finish_magnitude(c, signed) | (NEGATIVE_ZERO * (c < 0))


# ------------------------------------------------------------------------------------------ decoder


@pytest.mark.gl
@pytest.mark.parametrize("signed", [False, True], ids=["UF16", "SF16"])
@pytest.mark.parametrize("mode", [*range(1, 15), "reserved"])
def test_decoder_matches_mesa_and_openimageio(mode: int | str, signed: bool, tmp_path: Path,
                                              mesa: MesaBC6HDecoder) -> None:
    rng = np.random.default_rng([99 if mode == "reserved" else int(mode), int(signed)])
    spec = None if mode == "reserved" else bc6h.mode_spec(int(mode))
    blocks = random_blocks(rng, (48, 64), spec)  # 3,072 blocks, a 256x192 texture
    texture = BC6HTexture(256, 192, signed, (blocks,))
    path = tmp_path / "random.dds"
    write_dds(path, texture)

    ours = bc6h.decode_image(read_dds(path).levels[0], 256, 192, signed).view(np.uint16)
    by_mesa = decode_with_mesa(texture, mesa)[0].view(np.uint16)
    by_oiio = decode_with_oiio(path, 0).view(np.uint16)

    assert np.array_equal(ours, by_mesa), f"mode {mode}: {np.count_nonzero(ours != by_mesa)} texels differ from Mesa"
    # OpenImageIO returns +0 where the format yields -0 (SF16 values that round to magnitude 0 with a
    # negative sign; Mesa and Microsoft's finish_unquantize give 0x8000). Everything else is bit-exact.
    differ = ours != by_oiio
    assert np.all(ours[differ] == NEGATIVE_ZERO) and np.all(by_oiio[differ] == 0), f"mode {mode} differs from OIIO"
    if not signed:
        assert not differ.any()
    if spec is None:
        assert not ours.any(), "reserved modes must decode to zero"


def test_decoder_is_vectorised_over_leading_dimensions() -> None:
    rng = np.random.default_rng(3)
    blocks = random_blocks(rng, (2, 3, 5), bc6h.mode_spec(1))
    decoded = bc6h.decode_blocks(blocks, signed=False)
    assert decoded.shape == (2, 3, 5, 16, 3) and decoded.dtype == np.float16
    assert np.array_equal(decoded[1, 2], bc6h.decode_blocks(blocks[1, 2], signed=False))


def test_decoder_rejects_wrong_block_shape() -> None:
    with pytest.raises(ValueError, match="16"):
        bc6h.decode_blocks(np.zeros((4, 15), dtype=np.uint8), signed=False)


def test_layout_tables_cover_every_bit_once() -> None:
    """Each mode's layout uses 77 (two-region) or 65 (one-region) header bits with no bit used twice,
    and the stored field widths agree with the endpoint and delta precisions."""
    for spec in bc6h.MODES:
        fields = bc6h._parse_layout(spec.layout)
        header = 82 if spec.regions == 2 else 65
        assert len(fields) + (5 if spec.regions == 2 else 0) == header, spec.number
        assert len(set(fields)) == len(fields), spec.number
        for channel, name in enumerate("rgb"):
            assert sum(f == f"{name}0" for f, _ in fields) == spec.endpoint_bits
            stored = spec.delta_bits[channel]
            for endpoint in range(1, 2 * spec.regions):
                assert sum(f == f"{name}{endpoint}" for f, _ in fields) == stored, (spec.number, name, endpoint)


# ------------------------------------------------------------------------------------------ encoder


@pytest.mark.parametrize("signed", [False, True], ids=["UF16", "SF16"])
def test_mode10_encode_decode_reproduces_parameters(signed: bool) -> None:
    rng = np.random.default_rng(10 + signed)
    n = 20_000
    low, high = (-32, 31) if signed else (0, 63)
    endpoints = rng.integers(low, high + 1, (n, 2, 2, 3))
    index = rng.integers(0, 8, (n, 16))
    partition = rng.integers(0, 32, n)
    blocks = bc6h.encode_mode10(endpoints, index, partition, signed)

    decoded = bc6h.decode_blocks(blocks, signed).view(np.uint16)
    subset = bc6h.PARTITION_SUBSETS[partition]
    assert np.array_equal(decoded, expected_half_bits(endpoints, index, subset, 6, signed))
    # The anchor rule was exercised: about half the subsets had an anchor index >= 4 and were swapped.
    anchors = np.stack([np.zeros(n, dtype=np.int64), bc6h.SUBSET1_ANCHORS[partition]], 1)
    swapped = index[np.arange(n)[:, None], anchors] >= 4
    assert 0.4 < swapped.mean() < 0.6
    assert np.all(blocks[:, 0] & 0x1F == 0b11110)


@pytest.mark.parametrize("signed", [False, True], ids=["UF16", "SF16"])
def test_mode11_encode_decode_reproduces_parameters(signed: bool) -> None:
    rng = np.random.default_rng(20 + signed)
    n = 20_000
    low, high = (-512, 511) if signed else (0, 1023)
    endpoints = rng.integers(low, high + 1, (n, 2, 3))
    index = rng.integers(0, 16, (n, 16))
    blocks = bc6h.encode_mode11(endpoints, index, signed)

    decoded = bc6h.decode_blocks(blocks, signed).view(np.uint16)
    subset = np.zeros((n, 16), dtype=np.int64)
    assert np.array_equal(decoded, expected_half_bits(endpoints[:, None], index, subset, 10, signed))
    assert np.all(blocks[:, 0] & 0x1F == 0b00011)


@pytest.mark.parametrize("signed", [False, True], ids=["UF16", "SF16"])
@pytest.mark.parametrize("mode", range(1, 15))
def test_every_mode_encodes_what_it_decodes(mode: int, signed: bool) -> None:
    """Random parameters of every mode, endpoints drawn so that each lies within the delta window of any other
    (whichever end of subset 0 the anchor rule stores first), decode to exactly what they mean."""
    spec = bc6h.mode_spec(mode)
    rng = np.random.default_rng([mode, int(signed)])
    n = 4_000
    low, high = bc6h.endpoint_range(spec.endpoint_bits, signed)
    lowest, highest = bc6h.delta_window(spec)
    reach = np.minimum(np.minimum(-lowest, highest) // 2, (high - low) // 2)  # pairwise differences fit the window
    centre = rng.integers(low + reach, high - reach + 1, (n, 1, 1, 3))
    endpoints = np.clip(centre + rng.integers(-reach, reach + 1, (n, spec.regions, 2, 3)), low, high)
    index = rng.integers(0, 1 << spec.index_bits, (n, 16))
    partition = rng.integers(0, 32, n) if spec.regions == 2 else None
    blocks = bc6h.encode_blocks(mode, endpoints, index, partition, signed)

    decoded = bc6h.decode_blocks(blocks, signed).view(np.uint16)
    subset = bc6h.PARTITION_SUBSETS[partition] if spec.regions == 2 else np.zeros((n, 16), dtype=np.int64)
    assert np.array_equal(decoded, expected_half_bits(endpoints, index, subset, spec.endpoint_bits, signed))
    assert np.all(blocks[:, 0] & ((1 << spec.code_bits) - 1) == spec.code)


def test_encoder_rejects_endpoints_outside_the_delta_window() -> None:
    endpoints = np.array([[[[500, 500, 500], [516, 500, 500]]]])  # mode 12: 9-bit deltas reach 255 up
    index = np.zeros((1, 16), dtype=np.int64)
    bc6h.encode_blocks(12, endpoints, index, None, signed=False)
    endpoints[0, 0, 1, 0] = 500 + 256
    with pytest.raises(ValueError, match="delta window"):
        bc6h.encode_blocks(12, endpoints, index, None, signed=False)


def test_anchor_rule_on_a_hand_made_block() -> None:
    """Partition 17 has its subset-1 anchor at pixel 2; both anchors get index 7, so both subsets must be
    stored swapped and inverted, and the block still decodes to what was meant."""
    endpoints = np.array([[[[1, 2, 3], [60, 50, 40]], [[5, 6, 7], [33, 22, 11]]]])
    index = np.array([[7, 0, 7, 3, 1, 2, 5, 6, 0, 1, 2, 3, 4, 5, 6, 7]])
    partition = np.array([17])
    blocks = bc6h.encode_mode10(endpoints, index, partition, signed=False)
    expected = expected_half_bits(endpoints, index, bc6h.PARTITION_SUBSETS[partition], 6, False)
    assert np.array_equal(bc6h.decode_blocks(blocks, False).view(np.uint16), expected)
    # Stored r0 (bits 5..10) is the swapped endpoint 60, not 1.
    stored = int.from_bytes(blocks[0].tobytes(), "little")
    assert (stored >> 5) & 0x3F == 60


def test_encoder_rejects_out_of_range_parameters() -> None:
    ok_index, ok_partition = np.zeros((1, 16), dtype=np.int64), np.zeros(1, dtype=np.int64)
    with pytest.raises(ValueError, match="endpoints"):
        bc6h.encode_mode10(np.full((1, 2, 2, 3), 64), ok_index, ok_partition, signed=False)
    with pytest.raises(ValueError, match="index"):
        bc6h.encode_mode10(np.zeros((1, 2, 2, 3), dtype=np.int64), ok_index + 8, ok_partition, signed=False)
    with pytest.raises(ValueError, match="partition"):
        bc6h.encode_mode10(np.zeros((1, 2, 2, 3), dtype=np.int64), ok_index, ok_partition + 32, signed=False)
    with pytest.raises(ValueError, match="endpoints"):
        bc6h.encode_mode11(np.full((1, 2, 3), -513), ok_index, signed=True)
    with pytest.raises(TypeError):
        bc6h.encode_mode11(np.zeros((1, 2, 3)), ok_index, signed=False)


# ------------------------------------------------------------------------------ differentiable decode


@pytest.mark.parametrize("signed", [False, True], ids=["UF16", "SF16"])
@pytest.mark.parametrize("regions", [2, 1], ids=["mode10", "mode11"])
def test_differentiable_decode_forward_is_bit_exact(regions: int, signed: bool) -> None:
    """Continuous parameters (some outside the valid ranges) through the torch decode equal, bit for bit,
    the decoder's output for the blocks the encoder writes from the rounded parameters."""
    rng = np.random.default_rng(30 + 2 * regions + signed)
    n = 50_000
    spec = bc6h.MODE_10 if regions == 2 else bc6h.MODE_11
    low, high = bc6h.endpoint_range(spec.endpoint_bits, signed)
    endpoints = torch.tensor(rng.uniform(low - 2, high + 2, (n, regions, 2, 3)), dtype=torch.float32)
    # Exact integers and ties (x.5) included: the rounding rule must be the exporter's.
    ties = torch.tensor(rng.random((n // 4, regions, 2, 3)) < 0.5, dtype=torch.float32)
    endpoints[: n // 4] = torch.floor(endpoints[: n // 4]) + 0.5 * ties
    weights = torch.tensor(rng.uniform(-0.1, 1.1, (n, 16)), dtype=torch.float32)
    partition = torch.tensor(rng.integers(0, 32, n)) if regions == 2 else None

    values = block_decode.decode_blocks_differentiable(endpoints, weights, partition, signed)

    stored = block_decode.quantize_endpoints(endpoints, spec.endpoint_bits, signed).numpy().astype(np.int64)
    index = block_decode.quantize_weights(weights, spec.index_bits).numpy().astype(np.int64)
    if regions == 2:
        blocks = bc6h.encode_mode10(stored, index, partition.numpy(), signed)
    else:
        blocks = bc6h.encode_mode11(stored[:, 0], index, signed)
    reference = bc6h.decode_blocks(blocks, signed)
    assert values.dtype == torch.float32 and values.shape == (n, 16, 3)
    assert np.array_equal(values.numpy().astype(np.float16).view(np.uint16), reference.view(np.uint16))


@pytest.mark.parametrize("mode", [10, 11])
def test_closed_form_level_decode_matches_autograd(mode: int) -> None:
    """The training's level decode (closed form, image layout) gives the values of the autograd path bit for bit,
    arranged as the level's image, and its gradients to float rounding, for out-of-range parameters and rounding
    ties too; a one-region block's unused second segment gets no gradient."""
    rng = np.random.default_rng(41 + mode)
    bh, bw = 96, 160
    n = bh * bw
    spec = bc6h.mode_spec(mode)
    top = (1 << spec.endpoint_bits) - 1
    endpoints = torch.tensor(rng.uniform(-3.0, top + 3.0, (n, spec.regions, 2, 3)), dtype=torch.float32)
    endpoints[: n // 4] = torch.floor(endpoints[: n // 4]) + 0.5  # ties round up in both
    weights = torch.tensor(rng.uniform(-0.1, 1.1, (n, 16)), dtype=torch.float32)
    partition = torch.tensor(rng.integers(0, 32, n))
    modes = block_decode.BlockModes.of(torch.full((n,), mode), partition)
    upstream = torch.tensor(rng.normal(size=(3, 4 * bh, 4 * bw)), dtype=torch.float32)

    def as_image(texels: torch.Tensor) -> torch.Tensor:  # (n, 16, 3) -> (3, h, w), as BlockFeatures.level
        return texels.view(bh, bw, 4, 4, 3).permute(4, 0, 2, 1, 3).reshape(3, 4 * bh, 4 * bw)

    def two_segments(e: torch.Tensor) -> torch.Tensor:  # decode_level holds every block as two segments
        return e if spec.regions == 2 else torch.cat([e, e.detach()], dim=1)

    results = []
    for decode in (lambda e, w: block_decode.decode_level(two_segments(e), w, modes, bh, bw),
                   lambda e, w: as_image(block_decode.decode_blocks_differentiable(
                       e, w, partition if spec.regions == 2 else None, False))):
        e, w = endpoints.clone().requires_grad_(), weights.clone().requires_grad_()
        values = decode(e, w)
        values.backward(upstream)
        results.append((values.detach(), e.grad, w.grad))
    (fused, e_fused, w_fused), (general, e_general, w_general) = results
    assert torch.equal(fused, general)
    torch.testing.assert_close(e_fused, e_general, rtol=1e-5, atol=1e-6 * float(e_general.abs().max()))
    torch.testing.assert_close(w_fused, w_general, rtol=1e-5, atol=1e-6 * float(w_general.abs().max()))


def test_level_of_mixed_modes_decodes_as_its_encoded_blocks() -> None:
    """Blocks of all 14 modes in one level, endpoints spread wider than the delta windows allow and weights
    outside [0, 1]: the level decode equals, bit for bit, the decoder's output for the blocks the encoder writes
    from `quantize_blocks` (whose window clamp must follow the anchor rule for the encoder to accept them)."""
    rng = np.random.default_rng(44)
    bh, bw = 48, 64
    n = bh * bw
    mode = torch.tensor(rng.integers(1, 15, n))
    partition = torch.tensor(rng.integers(0, 32, n))
    modes = block_decode.BlockModes.of(mode, partition)
    top = modes.top.numpy().astype(np.float64)[:, None, None, None]
    centre = rng.uniform(0.0, 1.0, (n, 1, 1, 3)) * top
    endpoints = torch.tensor(centre + rng.uniform(-0.2, 0.2, (n, 2, 2, 3)) * top, dtype=torch.float32)
    weights = torch.tensor(rng.uniform(-0.1, 1.1, (n, 16)), dtype=torch.float32)

    image = block_decode.decode_level(endpoints, weights, modes, bh, bw)

    stored, index = block_decode.quantize_blocks(endpoints, weights, modes)
    fit = bc6h_partition.BlockFit(mode.numpy(), stored.numpy(), index.numpy(), partition.numpy(), np.zeros(n))
    blocks = bc6h_partition.encode_fit(fit, signed=False)
    reference = bc6h.decode_blocks(blocks, False).reshape(bh, bw, 4, 4, 3).transpose(4, 0, 2, 1, 3)
    assert np.array_equal(image.numpy().astype(np.float16).view(np.uint16),
                          reference.reshape(3, 4 * bh, 4 * bw).view(np.uint16))
    assert len(np.unique(bc6h.decode_blocks(blocks, False).view(np.uint16))) > 1000  # not a degenerate image


@pytest.mark.parametrize("signed", [False, True], ids=["UF16", "SF16"])
def test_differentiable_decode_gradients_fit_a_target(signed: bool) -> None:
    """Gradients are finite and useful: Adam through the emulated decode fits two-segment target blocks."""
    torch.manual_seed(0)
    rng = np.random.default_rng(40 + signed)
    n = 256
    true_endpoints = rng.integers(-25 if signed else 5, 26 if signed else 58, (n, 2, 2, 3))
    partition = torch.tensor(rng.integers(0, 32, n))
    target = block_decode.decode_blocks_differentiable(torch.tensor(true_endpoints, dtype=torch.float32),
                                               torch.tensor(rng.random((n, 16)), dtype=torch.float32),
                                               partition, signed)
    endpoints = torch.tensor(true_endpoints + rng.normal(0, 6, true_endpoints.shape), dtype=torch.float32,
                             requires_grad=True)
    weights = torch.full((n, 16), 0.5, requires_grad=True)
    optimiser = torch.optim.Adam([endpoints, weights], lr=0.05)
    losses = []
    for _ in range(300):
        loss = torch.mean((block_decode.decode_blocks_differentiable(endpoints, weights, partition, signed) - target) ** 2)
        optimiser.zero_grad()
        loss.backward()
        assert torch.isfinite(endpoints.grad).all() and torch.isfinite(weights.grad).all()
        optimiser.step()
        losses.append(loss.item())
    assert losses[-1] < 0.05 * losses[0], (losses[0], losses[-1])


def test_half_bits_to_value_is_eq9_and_exact() -> None:
    bits = np.arange(0, 0x7C00, dtype=np.uint16)
    values = block_decode.half_bits_to_value(torch.tensor(bits, dtype=torch.float32)).numpy()
    assert np.array_equal(values, bits.view(np.float16).astype(np.float32))
    # value_to_half_bits inverts it at every finite half.
    assert np.array_equal(bc6h.value_to_half_bits(values, signed=False), bits.astype(np.float64))


# --------------------------------------------------------------------------------- partition search


def test_partition_search_recovers_a_planted_partition() -> None:
    """Blocks made of two exact line segments (in the half-bit coordinate where BC6H interpolates) under a
    known partition: the search finds that partition with a residual of (numerically) zero."""
    rng = np.random.default_rng(50)
    n = 2_000
    partition = rng.integers(0, 32, n)
    subset = bc6h.PARTITION_SUBSETS[partition]
    rows = np.arange(n)[:, None]
    base = rng.uniform(8_000, 14_000, (n, 2, 3))
    direction = rng.uniform(-1_500, 1_500, (n, 2, 3))
    coords = base[rows, subset] + rng.random((n, 16, 1)) * direction[rows, subset]
    texels = block_decode.half_bits_to_value(torch.tensor(coords, dtype=torch.float64)).numpy()

    fit = bc6h_partition.fit_lines(texels, regions=2, signed=False)
    assert np.mean(fit.partition == partition) > 0.99
    assert np.all(fit.error[fit.partition == partition] < 1e-3)


def test_partition_search_picks_the_lowest_residual_of_all_32() -> None:
    rng = np.random.default_rng(51)
    texels = rng.random((300, 16, 3))
    fit = bc6h_partition.fit_lines(texels, regions=2, signed=False)
    x = bc6h.value_to_half_bits(texels, False)
    x = x - x.mean(1, keepdims=True)
    every = []
    for p in range(32):  # brute force over partitions (32 iterations, blocks stay vectorised)
        subset = np.broadcast_to(bc6h.PARTITION_SUBSETS[p], (300, 16))
        subset = np.ascontiguousarray(subset)
        ends, weights = bc6h_partition._fit_lines(x, subset, 2)
        every.append(((bc6h_partition.points_on_segments(ends, weights, subset) - x) ** 2).sum((1, 2)))
    best = np.min(np.stack(every, 1), axis=1)
    assert np.allclose(fit.error, best, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize(("modes", "floor_db"), [((10,), 33.0), ((11,), 40.0), (tuple(range(1, 15)), 43.0)],
                         ids=["mode10", "mode11", "auto"])
def test_encode_image_quality_on_a_real_texture(modes: tuple[int, ...], floor_db: float) -> None:
    """The bundled real albedo (256x256): mode 11 should be near-transparent, mode 10 (6-bit endpoints) clearly
    worse but usable, and every mode per block best. Floors are a few dB under what was measured (36.11, 41.85
    and 44.80 dB)."""
    image = read_rgb(SAMPLE_ALBEDO)
    blocks = bc6h_partition.encode_image(image, modes)
    decoded = bc6h.decode_image(blocks, 256, 256, signed=False)
    assert psnr(image, decoded) > floor_db


def test_fit_blocks_keeps_the_best_mode_and_reports_its_exact_error() -> None:
    """Each block of a real texture takes the candidate mode with the lowest error, the error is that of the
    blocks as encoded (decoded bit-exactly, in the half-bit domain), and more candidates never fit worse."""
    texels = bc6h.image_to_block_texels(read_rgb(SAMPLE_ALBEDO)[:128, :128].astype(np.float64)).reshape(-1, 16, 3)
    every = tuple(range(1, 15))
    fits = {modes: bc6h_partition.fit_blocks(texels, modes, signed=False) for modes in [(11,), (10,), (6,), every]}
    target = bc6h.value_to_half_bits(texels, False)
    for modes, fit in fits.items():
        decoded = bc6h.decode_blocks(bc6h_partition.encode_fit(fit, signed=False), False)
        error = ((bc6h.value_to_half_bits(decoded.astype(np.float64), False) - target) ** 2).sum((1, 2))
        assert np.allclose(error, fit.error, rtol=1e-9, atol=1e-6), modes
        assert set(np.unique(fit.mode)) <= set(modes)
    threaded = bc6h_partition.fit_blocks(texels, every, signed=False, chunk=100, workers=3)
    assert all(np.array_equal(getattr(threaded, f), getattr(fits[every], f)) for f in ("mode", "endpoints", "index"))
    best_single = np.minimum.reduce([fits[m].error for m in [(11,), (10,), (6,)]])
    assert np.all(fits[every].error <= best_single + 1e-6)
    assert len(np.unique(fits[every].mode)) >= 4  # a real texture uses several modes


@pytest.mark.gl
def test_dds_mip_chain_of_a_real_1024x512_texture(tmp_path: Path, mesa: MesaBC6HDecoder) -> None:
    """A non-square 1024x512 texture (the bundled real albedo tiled 4x2), its full mip chain down to 1x1
    encoded in mode 10, written as DDS and read back by our reader, OpenImageIO and Mesa: all three agree
    with our decoder on every level."""
    image = np.tile(read_rgb(SAMPLE_ALBEDO), (2, 4, 1))
    assert image.shape == (512, 1024, 3)
    chain = mip_chain(image)
    assert len(chain) == full_mip_count(1024, 512)
    levels = [bc6h_partition.encode_image(level_image, (10,)) for level_image in chain]
    texture = BC6HTexture(1024, 512, False, tuple(levels))
    path = tmp_path / "bricks.dds"
    write_dds(path, texture)

    read_back = read_dds(path)
    by_mesa = decode_with_mesa(read_back, mesa)
    for level in range(len(levels)):
        w, h = mip_size(1024, 512, level)
        ours = bc6h.decode_image(read_back.levels[level], w, h, signed=False)
        assert ours.shape == (h, w, 3)
        assert np.array_equal(ours.view(np.uint16), decode_with_oiio(path, level).view(np.uint16)), level
        assert np.array_equal(ours.view(np.uint16), by_mesa[level].view(np.uint16)), level
    assert psnr(image, bc6h.decode_image(read_back.levels[0], 1024, 512, False)) > 30.0
