"""The layers import downward only (docs/ARCHITECTURE.md): a short AST check of every import in the tree,
function-local ones included.

- `bcf.core` imports nothing of jobs, service, engine or the CLI; inside it, a sub-package imports only its own
  layer and those below (base < codec < material < fit < export < report < pipeline).
- Outside core, code uses `bcf.core`'s public API (`from bcf.core import name`), never its modules.
- `bcf.engine` imports only core; `bcf.jobs` imports core and jobs, never the service or the CLI.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import bcf.core

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"core": "bcf.core", "engine": "bcf.engine", "jobs": "bcf.jobs", "service": "bcf.service", "cli": "bcf"}
# Core's layers, lowest first; the base modules are the vocabulary every layer shares.
CORE_LAYERS = (("options", "errors", "files", "psnr", "resources", "version"), ("codec",), ("material",), ("fit",), ("export",),
               ("report",), ("pipeline",))
# Which top-level parts each part may import (besides itself).
ALLOWED = {"core": set(), "engine": {"core"}, "jobs": {"core"}, "service": {"core", "jobs"},
           "cli": {"core", "engine", "jobs", "service"}}


def _module_name(path: Path) -> str:
    folder, *rest = path.relative_to(ROOT).with_suffix("").parts
    parts = [FOLDERS[folder], *rest]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, imported module, names) of every `import` / `from ... import` in the file, resolved to absolute."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            found.append((node.lineno, base, [alias.name for alias in node.names]))
    return [(line, name, names) for line, name, names in found if name == "bcf" or name.startswith("bcf.")]


def _part(module: str) -> str:
    """core, engine, jobs, service or cli (the `bcf` root and its command modules)."""
    second = module.split(".")[1] if "." in module else ""
    return second if second in ("core", "engine", "jobs", "service") else "cli"


def _core_layer(module: str) -> int:
    name = module.split(".")[2] if module.count(".") >= 2 else ""
    return next(i for i, names in enumerate(CORE_LAYERS) if name in names)


def _violations(path: Path) -> list[str]:
    module = _module_name(path)
    part = _part(module)
    problems = []
    for line, target, names in _imports(path):
        where = f"{path.relative_to(ROOT)}:{line}: {target}"
        target_part = _part(target) if target != "bcf" else "cli"
        if target_part != part and target_part not in ALLOWED[part]:
            problems.append(f"{where}: {part} must not import {target_part}")
        elif part == "core" and module != "bcf.core" and target.startswith("bcf.core."):
            if _core_layer(target) > _core_layer(module):
                problems.append(f"{where}: a lower core layer imports a higher one")
        elif part != "core" and target_part == "core":
            private = [n for n in names if n not in bcf.core.__all__] if target == "bcf.core" else [target]
            if private:
                problems.append(f"{where}: outside core, import bcf.core's public API only ({', '.join(private)})")
    return problems


SOURCES = sorted(p for folder in FOLDERS for p in (ROOT / folder).rglob("*.py"))


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_point_down_the_layers(path: Path) -> None:
    assert _violations(path) == []


def test_the_check_catches_upward_imports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The rules fire: a fake tree whose modules import upward yields one violation each."""
    for folder in FOLDERS:
        (tmp_path / folder).mkdir()
    cases = {
        "core/codec/x.py": "from bcf.core.fit import model",  # lower core layer -> higher
        "core/y.py": "import bcf.jobs.queue",  # core -> jobs
        "jobs/z.py": "from bcf.service import app",  # jobs -> service
        "engine/w.py": "from bcf.core.fit.model import Decoder",  # reaching into core's modules
        "service/v.py": "def f():\n    from bcf import material_cli",  # service -> CLI, function-local
    }
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    for name, text in cases.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")
        assert len(_violations(path)) == 1, name


def test_public_api_names_resolve() -> None:
    """Every name `bcf.core` promises loads from its module."""
    for name in bcf.core.__all__:
        assert getattr(bcf.core, name) is not None, name
