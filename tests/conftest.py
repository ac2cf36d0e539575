"""Shared fixtures: one Mesa (llvmpipe, EGL) OpenGL context per test process, a small real export, a private
redis-server."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import pytest
import torch

from bcf.core import pipeline
from bcf.core.material import images
from bcf.core.material.texture_set import load_material
from bcf.core.options import CompressOptions
from reference_decoders import MesaBC6HDecoder, MesaUnavailable
from service_harness import redis_server

SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "sample"


@pytest.fixture(scope="session")
def mesa() -> Iterator[MesaBC6HDecoder]:
    try:
        decoder, problem = MesaBC6HDecoder(), ""
    except MesaUnavailable as exc:
        decoder, problem = None, str(exc)
    if decoder is None:  # fail, never skip: a missing driver must not let CI pass silently
        pytest.fail(f"Mesa's llvmpipe through EGL is required for @pytest.mark.gl tests: {problem} "
                    "(install libegl1 libgl1-mesa-dri libegl-mesa0)", pytrace=False)
    yield decoder
    decoder.close()


@pytest.fixture(scope="module")
def export_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A real `compress_material` output of a 64x64 crop of the bundled sample (few iterations)."""
    source = tmp_path_factory.mktemp("material") / "sample_64"
    source.mkdir()
    for name in ("albedo.png", "normal_gl.png", "arm.png"):
        images.write_rgb(source / name, images.read_rgb(SAMPLE / name)[:64, :64], png_bits=8)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        folder = tmp_path_factory.mktemp("out") / "out"
        options = CompressOptions(preset="fast", phase1_iterations=20, phase2_iterations=20, batch_size=1024)
        pipeline.compress_material(load_material(source), options, folder)
    finally:
        torch.set_num_threads(threads)
    yield folder


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A private redis-server for the module (each xdist worker process starts its own)."""
    process, url = redis_server(tmp_path_factory.mktemp("redis"))
    try:
        yield url
    finally:
        process.stop()
