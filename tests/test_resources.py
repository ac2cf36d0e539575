"""The memory estimate that the CLI and the service check from image headers before decoding any pixel."""

from __future__ import annotations

import pytest

from bcf.core import CompressOptions, MemoryBudgetError, check_memory, estimate_peak_memory, resolve_options

GIB = 2**30


def test_the_default_budget_of_a_24_gib_machine_allows_8k_textures() -> None:
    """The pixel limit's default (8192²) and the memory check's default budget (the machine's memory) agree."""
    for preset in ("fast", "default"):
        assert estimate_peak_memory(8192, 8192, resolve_options(CompressOptions(preset=preset))) < 24 * GIB


def test_the_estimate_grows_with_the_texels_and_with_the_training_batch() -> None:
    fast = resolve_options(CompressOptions(preset="fast"))  # no training step: the batch costs nothing
    assert estimate_peak_memory(2048, 2048, fast) == estimate_peak_memory(
        2048, 2048, resolve_options(CompressOptions(preset="fast", batch_size=1 << 20)))
    small, large = (resolve_options(CompressOptions(preset="default", batch_size=b)) for b in (1 << 12, 1 << 22))
    assert estimate_peak_memory(1024, 1024, small) < estimate_peak_memory(1024, 1024, large)
    assert estimate_peak_memory(1024, 1024, small) < estimate_peak_memory(2048, 2048, small)


def test_over_the_budget_is_an_input_error_naming_the_setting() -> None:
    options = resolve_options(CompressOptions(preset="default"))
    needed = estimate_peak_memory(4096, 4096, options)
    assert check_memory(4096, 4096, options, needed, "BCF_JOB_MEMORY_MB") == needed
    with pytest.raises(MemoryBudgetError, match=r"4096x4096 .* GiB of memory, more than the budget .*BCF_JOB_MEMORY_MB"):
        check_memory(4096, 4096, options, needed - 1, "BCF_JOB_MEMORY_MB")
