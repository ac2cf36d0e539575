"""Property tests: a real export's manifest.json and report.json (and a `bcf check` baseline) damaged in every
way hypothesis finds (values replaced by other JSON: huge or negative numbers, NaN, infinities, strings,
absolute and '../' paths, nulls; keys dropped or added; the file truncated, or not UTF-8), then read by
`bcf info`, `bcf decode` and `bcf check`. Each command either works (the damage was harmless) or fails as a
user error: exit 2, one `bcf: error:` line on stderr, no traceback. `bcf check` may also exit 1 (a damaged
baseline can make the report look worse).

The commands run in-process through `bcf.cli.main` (the console script's own entry point): a subprocess per
example would cost a second each.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path
from typing import Any, Union

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bcf.cli import main
from bcf.core import MANIFEST_FILE, REPORT_FILE

# Derandomised: the same examples on every run, so CI cannot pass or fail by luck; no example database.
PROPERTIES = settings(max_examples=200, deadline=None, derandomize=True, database=None,
                      suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

Json = Union[None, bool, int, float, str, list["Json"], dict[str, "Json"]]
Path_ = tuple[Union[str, int], ...]


# ------------------------------------------------------------------------------------------- mutations

_NUMBERS = st.one_of(st.integers(), st.sampled_from([-1, 0, 2**31, 2**63, 2**64, -(2**63) - 1, 10**400]),
                     st.floats(allow_nan=True, allow_infinity=True))
_TEXTS = st.one_of(st.text(max_size=20), st.sampled_from([
    "", ".", "..", "/etc/passwd", "../manifest.json", "../../outside.dds", "sub/features_0.dds", "C:\\x.dds",
    "features_1.dds", "decoder.bin", "manifest.json", "report.json", "a\x00b", "NaN", "Infinity", "-inf",
    "1e999", "0" * 64, "\ud800"]))
_SCALARS = st.one_of(st.none(), st.booleans(), _NUMBERS, _TEXTS)
_VALUES: st.SearchStrategy[Json] = st.recursive(
    _SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=8), inner,
                                                                                   max_size=3)), max_leaves=6)


def _like(value: Json) -> st.SearchStrategy[Json]:
    """Other values of `value`'s kind: numbers for a number, strings for a string."""
    if isinstance(value, bool) or value is None:
        return _SCALARS
    if isinstance(value, (int, float)):
        return _NUMBERS
    if isinstance(value, str):
        return _TEXTS
    return _VALUES


def _paths(value: Json, prefix: Path_ = ()) -> list[Path_]:
    """Every place in a JSON document: the root, each key of each object, each item of each array."""
    found = [prefix]
    if isinstance(value, dict):
        for key, item in value.items():
            found += _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            found += _paths(item, (*prefix, index))
    return found


def _parent(document: Json, path: Path_) -> Any:
    for step in path[:-1]:
        document = document[step]  # type: ignore[index]
    return document


@st.composite
def mutated(draw: st.DrawFn, original: Json) -> bytes:
    """The document's bytes after one to three edits of its values or keys, or damage to its text."""
    document = json.loads(json.dumps(original))
    for _ in range(draw(st.integers(1, 3))):
        places = _paths(document)
        path = draw(st.sampled_from(places))
        edit = draw(st.sampled_from(["replace", "drop", "add"]))
        if not path:
            document = draw(_VALUES) if edit == "replace" else document
            continue
        parent, key = _parent(document, path), path[-1]
        if edit == "replace":  # mostly a value of the same kind: a document that still parses gets further
            parent[key] = draw(st.one_of(_like(parent[key]), _like(parent[key]), _VALUES))
        elif edit == "drop":
            del parent[key]
        elif isinstance(parent, dict):
            parent[draw(st.text(max_size=12))] = draw(_VALUES)
        else:
            parent.insert(key, draw(_VALUES))
    text = json.dumps(document, indent=2).encode()  # NaN and Infinity as Python writes them; \ud800 escaped
    damage = draw(st.sampled_from(["none"] * 6 + ["truncate", "bytes"]))
    if damage == "truncate":
        return text[:draw(st.integers(0, max(len(text) - 1, 0)))]
    if damage == "bytes":
        at = draw(st.integers(0, len(text)))
        return text[:at] + draw(st.sampled_from([b"\xff\xfe", b"\x80", b"\xc3", b"\x00"])) + text[at:]
    return text


# ------------------------------------------------------------------------------------------- the commands


def bcf(*args: object) -> tuple[int, str, str]:
    """`bcf ARGS` in this process: (exit code, stdout, stderr). An exception `main` lets through is a bug
    (the console script would print its traceback), so it propagates and fails the test."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


def assert_works_or_one_error_line(result: tuple[int, str, str], allowed: frozenset[int] = frozenset({0})) -> None:
    code, _, stderr = result
    assert "Traceback" not in stderr, stderr
    if code == 2:
        lines = stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("bcf: error: "), stderr
    else:
        assert code in allowed, (code, stderr)


def _copy(export_folder: Path, target: Path) -> Path:
    """A fresh copy of the export (the commands only read it; decode writes elsewhere)."""
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(export_folder, target)
    return target


def _original(export_folder: Path, name: str) -> Json:
    return json.loads((export_folder / name).read_text())


def test_manifest_mutations_are_harmless_or_one_error_line(export_folder: Path, tmp_path: Path) -> None:
    @PROPERTIES
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        folder = _copy(export_folder, tmp_path / "export")
        damaged = data.draw(mutated(_original(export_folder, MANIFEST_FILE)), "manifest")
        (folder / MANIFEST_FILE).write_bytes(damaged)
        assert_works_or_one_error_line(bcf("info", folder))
        decoded = tmp_path / "decoded"
        shutil.rmtree(decoded, ignore_errors=True)
        assert_works_or_one_error_line(bcf("decode", folder, "-o", decoded))

    check()


def test_report_and_baseline_mutations_are_harmless_or_one_error_line(export_folder: Path, tmp_path: Path) -> None:
    report = _original(export_folder, REPORT_FILE)

    @PROPERTIES
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        folder = _copy(export_folder, tmp_path / "export")
        (folder / REPORT_FILE).write_bytes(data.draw(mutated(report), "report"))
        good = tmp_path / "good.json"
        good.write_text(json.dumps(report))
        assert_works_or_one_error_line(bcf("info", folder))
        assert_works_or_one_error_line(bcf("check", folder, "--baseline", good), frozenset({0, 1}))
        baseline = tmp_path / "baseline.json"
        baseline.write_bytes(data.draw(mutated(report), "baseline"))
        assert_works_or_one_error_line(bcf("check", export_folder, "--baseline", baseline), frozenset({0, 1}))

    check()


def test_an_undamaged_export_passes_every_command(export_folder: Path, tmp_path: Path) -> None:
    """The baseline of the properties: without damage, every command works."""
    assert bcf("info", export_folder)[0] == 0
    assert bcf("decode", export_folder, "-o", tmp_path / "decoded")[0] == 0
    assert bcf("check", export_folder, "--baseline", export_folder / REPORT_FILE)[0] == 0
