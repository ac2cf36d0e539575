"""Shared fixtures: one Mesa (llvmpipe, EGL) OpenGL context per test process."""

from __future__ import annotations

from typing import Iterator

import pytest

from reference_decoders import MesaBC6HDecoder, MesaUnavailable


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
