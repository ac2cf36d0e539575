"""bcf.core: the library. Files -> texture set -> fit -> exported artifacts -> reference decode -> report.

Sub-packages, each importing only those before it (tests/test_architecture.py checks it):

    options, errors, files, psnr, resources, version   the vocabulary every layer shares
    codec      BC6H blocks and DDS/KTX2 files (numpy only)
    material   image files -> the validated 8-channel `TextureSet`; asset-tree scans
    fit        sampling, the neural material, the differentiable BC6H decode, the two-phase training
    export     the exported files (docs/FORMAT.md) and the one reference decoder that reads them back
    report     metrics of the decoded files, report.json / report.html, baselines, the regression check
    pipeline   all of the above strung together: `compress_material`, and whether a result is current

The names below are the public API: the CLI, the job queue, the HTTP service and the engine tools import them
from `bcf.core` and never reach into the modules. They load on first use, so `import bcf.core` stays cheap
(torch loads with the first name that needs it).
"""

from __future__ import annotations

import importlib
from typing import Any

_PUBLIC: dict[str, tuple[str, ...]] = {
    "bcf.core.version": ("GENERATOR", "__version__"),
    "bcf.core.errors": ("InputError", "failure_text"),
    "bcf.core.files": ("atomic_path", "file_sha256", "replace_folder", "staging_folder", "staging_leftovers",
                       "write_text_atomic"),
    "bcf.core.psnr": ("psnr_from_mse",),
    "bcf.core.resources": ("MemoryBudgetError", "check_memory", "estimate_peak_memory", "physical_memory"),
    "bcf.core.options": ("BASELINES", "PRESETS", "Address", "CompressOptions", "Device", "FeatureSize",
                         "JobOptions", "Preset", "ResolvedOptions", "parse_baselines", "resolve_options"),
    "bcf.core.codec.containers": ("BC6HTexture", "ContainerError", "full_mip_count", "mip_size", "read_dds",
                                  "read_texture", "write_dds", "write_ktx2"),
    "bcf.core.codec.bc6h": ("decode_image",),
    "bcf.core.codec.textures": ("container_kind", "encode_mips", "encoder_modes", "format_name", "mode_histogram",
                                "to_bc6h_range", "verify_texture"),
    "bcf.core.material.images": ("ImageReadError", "ImageWriteError", "WRITE_EXTENSIONS", "mip_chain", "read_image",
                                 "read_rgb", "write_rgb"),
    "bcf.core.material.roles": ("IMAGE_EXTENSIONS", "ROLES", "TEXTURES", "MaterialError", "MaterialFiles",
                                "NormalConvention", "Role", "material_images"),
    "bcf.core.material.naming": ("discover_material", "normal_convention_from_name", "resolve_material"),
    "bcf.core.material.texture_set": ("MAX_TEXTURE_PIXELS", "InspectedMaterial", "MaterialSource", "TextureSet",
                                      "decode_texture_set", "inspect_texture_set", "load_material",
                                      "load_texture_set"),
    "bcf.core.material.assets": ("AssetScan", "FoundMaterial", "scan_assets"),
    "bcf.core.fit.training": ("DeviceUnavailableError", "ProgressCallback", "StopCallback", "TrainingProgress",
                              "TrainingStopped", "require_device"),
    "bcf.core.export.artifacts": ("DECODER_FILE", "MANIFEST_FILE", "ExportError", "Manifest", "read_manifest",
                                  "verify_files"),
    "bcf.core.export.decode": ("ExportedMaterial", "decode_export", "decoded_file_names", "load_export",
                               "render_mip"),
    "bcf.core.report.report_json": ("REPORT_FILE", "MipMetrics", "Report", "ReportError", "format_report",
                                    "read_report"),
    "bcf.core.report.html": ("HTML_REPORT_FILE",),
    "bcf.core.report.check": ("CheckError", "CheckRow", "compare_reports", "format_check"),
    "bcf.core.pipeline": ("BASELINES_FOLDER", "OutputExistsError", "ResultIdentity", "check_output",
                          "compress_material", "is_current", "result_identity"),
}
_MODULE_OF = {name: module for module, names in _PUBLIC.items() for name in names}
__all__ = sorted(_MODULE_OF)


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'bcf.core' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return __all__
