"""What one compression needs of the machine, known from the image headers before any pixel is decoded.

`estimate_peak_memory` is a fit to measured peak resident memory of `bcf compress` (the whole job: loading,
the principal-component start, block fitting, training, export, evaluation and the HTML report; one torch
thread; docs/BENCHMARKS.md "Memory per job"): a fixed part (the interpreter, torch, the libraries), a part per
texel of the material, and a part per training sample of a batch. The CLI and the job service refuse a material
whose estimate is over their budget, so a large texture is a clear error up front rather than a process killed
by the kernel half way.
"""

from __future__ import annotations

import os

from bcf.core.errors import InputError
from bcf.core.options import ResolvedOptions

__all__ = ["FIXED_BYTES", "PER_SAMPLE_BYTES", "PER_TEXEL_BYTES", "MemoryBudgetError", "check_memory",
           "estimate_peak_memory", "physical_memory"]

# Measured peak resident memory of `bcf compress` (wood_peeling_paint_weathered scaled to 512² .. 4096², one torch
# thread, docs/BENCHMARKS.md "Memory per job"): fast 0.60 / 0.85 / 1.73 / 4.84 GB, default 1.80 GB at 2048² and
# 4.93 GB at 4096²: 250-260 B a texel above 1K. Rounded up: 8192² with the default preset estimates 19.5 GB.
FIXED_BYTES = 600 * 10**6
PER_TEXEL_BYTES = 280
# Training's buffers grow with the batch: sampled features, activations and their gradients per sample
# (measured 620-760 B a sample between batches of 2^16 and 2^20 at 512²; rounded up).
PER_SAMPLE_BYTES = 1_200


class MemoryBudgetError(InputError):
    """A material whose compression would need more memory than the budget allows."""


def estimate_peak_memory(width: int, height: int, options: ResolvedOptions) -> int:
    """Estimated peak resident bytes of compressing a width x height material with `options`."""
    trains = options.phase1_iterations + options.phase2_iterations > 0
    return FIXED_BYTES + PER_TEXEL_BYTES * width * height + (PER_SAMPLE_BYTES * options.batch_size if trains else 0)


def physical_memory() -> int:
    """Bytes of memory of this machine (the budget when none is set)."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(width: int, height: int, options: ResolvedOptions, budget_bytes: int, setting: str) -> int:
    """The estimate, or MemoryBudgetError when it is over `budget_bytes`; `setting` names what sets the budget
    (a CLI flag or a service setting), for the message."""
    needed = estimate_peak_memory(width, height, options)
    if needed > budget_bytes:
        batch = f" (training batches of {options.batch_size})" if options.phase1_iterations + options.phase2_iterations else ""
        raise MemoryBudgetError(
            f"compressing a {width}x{height} material{batch} needs an estimated "
            f"{needed / 2**30:.1f} GiB of memory, more than the budget of {budget_bytes / 2**30:.1f} GiB ({setting})",
            fix="use smaller textures, a smaller batch size, or a machine with more memory")
    return needed
