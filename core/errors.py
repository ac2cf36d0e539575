"""The one error type for problems with what a user gave: a file, a folder, an option.

It carries fields, not finished prose for one audience: the CLI words `options` as flags (`--force`), the
HTTP service as request fields, and each names the file as its user knows it. Every module's own error
(`MaterialError`, `ExportError`, ...) is an `InputError`, so callers catch one type.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence, Union

__all__ = ["InputError", "failure_text"]

OptionWording = Callable[[Sequence[str]], str]
OptionGroup = Union[str, Sequence[str]]


def _field_names(options: Sequence[str]) -> str:
    return "/".join(options)


class InputError(ValueError):
    """A problem the user can fix.

    file: the file or folder at fault (None when the problem is not one file's).
    role: the texture role concerned (albedo, normal, arm, ao, roughness, metalness), if any.
    reason: what is wrong, one line, naming other files by their names only; `{}` where options go.
    fix: how to fix it (e.g. "use {} to replace it"), or "".
    options: what fills the `{}` of reason and fix, in order: each an option name as the pydantic models spell
        it (`force`, `normal_convention`, `albedo`), or a group of names that are alternatives.
    """

    def __init__(self, reason: str, *, file: Union[Path, str, None] = None, role: Optional[str] = None,
                 fix: str = "", options: Sequence[OptionGroup] = ()):
        self.reason, self.file, self.role, self.fix = reason, file, role, fix
        self.options = tuple((group,) if isinstance(group, str) else tuple(group) for group in options)
        super().__init__(self.message())

    def message(self, options: OptionWording = _field_names,
                file: Callable[[Union[Path, str]], str] = str) -> str:
        """One line: `<file>: <reason> (<fix>)`, with the options and the file worded by the caller."""
        text = self.reason + (f" ({self.fix})" if self.fix else "")
        # Fill each "{}" in turn; other braces (a file name may hold some) stay as they are.
        if self.options:
            first, *rest = text.split("{}")
            worded = [options(group) for group in self.options] + [""] * len(rest)
            text = first + "".join(option + part for option, part in zip(worded, rest))
        return f"{file(self.file)}: {text}" if self.file is not None else text


def failure_text(exc: BaseException, file: Callable[[Union[Path, str]], str] = str) -> str:
    """One line for a compression that failed (a batch item, a job's `error`): an input problem as its message
    with files worded by `file`, any other error with its type, since then it is bcf's fault, not the input's."""
    if isinstance(exc, InputError):
        return exc.message(file=file)
    return str(exc) if isinstance(exc, (ValueError, OSError)) else f"{type(exc).__name__}: {exc}"
