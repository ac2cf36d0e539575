"""bcf.engine: what a game engine team sees of an export: generated GLSL/HLSL decoders (`shader`), a headless
OpenGL context that samples the BC6H files with real hardware filtering (`gl`), and the lit-sphere `preview`.
It reads exports through `bcf.core`'s public API only.
"""
