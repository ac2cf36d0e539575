"""The `bcf` command line: a thin layer over `bcf.core` (and `bcf.jobs`, `bcf.service`, `bcf.engine`).

Each command is a typed function whose signature cyclopts turns into flags; its docstring is its help. Options
the library's pydantic models define (`JobOptions`, `MaterialFiles`) are not declared again: a parameter of the
model's type, annotated with `model_flags(...)`, becomes one flag per named field, with the field's type,
default, choices, constraints and description.

Exit codes: 0 success, 1 `check` found something worse or `batch` had failures, 2 user error (one line
`bcf: error: ...` on stderr), 130 interrupted.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Annotated, Callable, Optional, Sequence

import pydantic
from cyclopts import App, CycloptsError, Group, Parameter
from cyclopts.argument import ArgumentCollection

from bcf.core import InputError, __version__

Output = Annotated[Path, Parameter(name=["-o", "--output"])]
OptionalOutput = Annotated[Optional[Path], Parameter(name=["-o", "--output"])]
Quiet = Annotated[bool, Parameter(name=["-q", "--quiet"], help="no progress display")]


def model_flags(*fields: str, group: Group | str = "Parameters") -> Parameter:
    """Flatten a pydantic-model parameter into one flag per field of `fields`; its other fields keep the
    model's defaults. The parameter must be named `options` or `files`: cyclopts matches the `parse`
    pattern against the parameter's own name as well as each field's."""
    return Parameter(name="*", group=group, parse=re.compile(rf"^(options|files|{'|'.join(fields)})$"))


def _one_at_most(arguments: ArgumentCollection) -> None:
    given = [argument.name for argument in arguments if argument.tokens]
    if len(given) > 1:
        raise ValueError(f"{given[1]} not allowed with {given[0]}")


# A command's options that exclude each other (`--levels`/`--no-mips`, `--mip`/`--all-mips`).
EXCLUSIVE = Group("", validator=_one_at_most, show=False)


def flags(names: Sequence[str]) -> str:
    """Option names as the models spell them (`normal_convention`) -> flags (`--normal-convention`)."""
    return "/".join("--" + name.replace("_", "-") for name in names)


def say(message: str = "") -> None:
    print(message, flush=True)  # flush: progress should show while the next step runs


def clock(seconds: float) -> str:
    seconds = int(round(max(seconds, 0.0)))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def check_output_file(path: Path, allowed: Sequence[str], what: str) -> str:
    """Fail early (before any work) on an output file that cannot be right; returns its lower-case suffix."""
    suffix = path.suffix.lower()
    if suffix not in allowed:
        raise InputError(f"unsupported {what} extension {suffix or '(none)'!r}; use {' or '.join(allowed)}",
                         file=path)
    if path.is_dir():
        raise InputError("is a directory", file=path)
    return suffix


# ------------------------------------------------------------------------------------------------- main


def build_app() -> App:
    # The command modules import torch-heavy names inside the commands: `bcf --help`, `--version` and argument
    # errors never load torch.
    from bcf import admin_cli, batch_cli, bc6h_cli, material_cli, preview_cli, service_cli

    def summary(command: Callable[..., int]) -> str:  # the docstring's first clause: one line on the top page
        return re.split(r" \(|:", (command.__doc__ or "").strip().splitlines()[0])[0].rstrip(".")

    # Plain text for the top page, so its list of bc6h commands keeps its lines; Markdown for the commands' own
    # pages, so their docstrings' paragraphs are re-wrapped to the terminal.
    app = App(name="bcf", version=f"bcf {__version__}", version_flags=["--version"], help_format="plaintext",
              suppress_keyboard_interrupt=False,  # main() says what the command kept
              # no generated --no-FLAG for each flag, and no "[default: False]" on flags
              default_parameter=Parameter(negative=(), show_default=lambda value: None if value is False else value),
              help="Neural block-compressed features (BC6H) for PBR materials.\n\nbc6h commands:\n" +
                   "\n".join(f"  bc6h {c.__name__:<8} {summary(c)}" for c in bc6h_cli.COMMANDS))
    for module in (material_cli, preview_cli, batch_cli, service_cli):
        for command in module.COMMANDS:
            app.command(command, help_format="markdown")
    bc6h = App(name="bc6h", help="BC6H textures: encode, decode, info", help_format="markdown")
    for command in bc6h_cli.COMMANDS:
        bc6h.command(command)
    app.command(bc6h)
    admin = App(name="admin", help="Maintenance of the service's data folder: recover", help_format="markdown")
    for command in admin_cli.COMMANDS:
        admin.command(command)
    app.command(admin)
    for parent, prog in ((app, "bcf"), (bc6h, "bcf bc6h"), (admin, "bcf admin")):
        parent.default(_no_command(prog))
    return app


def _no_command(prog: str) -> Callable[..., int]:
    """What runs when no command, or an unknown word, follows `prog`."""
    def missing(*words: Annotated[str, Parameter(show=False)]) -> int:
        problem = f"unknown command {words[0]!r}" if words else "the following arguments are required: COMMAND"
        raise InputError(f"{problem} (see '{prog} --help')")
    return missing


def _invalid(exc: pydantic.ValidationError) -> str:
    """A model's validation errors, each naming its flag (a check of the whole model names none); a validator's
    own message is kept whole."""
    def text(error: dict) -> str:
        message = error["ctx"]["error"] if error["type"] == "value_error" else error["msg"]
        return f"{flags([str(error['loc'][-1])])}: {message}" if error["loc"] else str(message)
    return "; ".join(text(e) for e in exc.errors())


def _message(exc: BaseException) -> str:
    if isinstance(exc, CycloptsError):
        text = _invalid(exc.__cause__) if isinstance(exc.__cause__, pydantic.ValidationError) else str(exc)
        return f"{text} (see '{' '.join(['bcf', *(exc.command_chain or ())])} --help')"
    if isinstance(exc, pydantic.ValidationError):
        return _invalid(exc)
    if isinstance(exc, InputError):
        return exc.message(options=flags)
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    return str(exc)


def _one_line(text: str) -> str:
    """`text` with every unprintable character escaped (\\n, \\x1e, \\x85): a message may quote a damaged
    file's keys or values, and the error must stay one line."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run `bcf` with `argv` (default: sys.argv[1:]) and return the exit code."""
    try:
        code = build_app()(list(sys.argv[1:] if argv is None else argv), exit_on_error=False, print_error=False,
                           result_action="return_value")
        return code or 0  # --help and --version return None
    # Errors the user can fix; anything else is a bug in bcf and keeps its traceback.
    except (CycloptsError, InputError, OSError, pydantic.ValidationError) as exc:
        print(f"bcf: error: {_one_line(_message(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # a command may say what it kept: KeyboardInterrupt("...")
        print("bcf: interrupted" + (f"; {exc}" if exc.args else ""), file=sys.stderr)
        return 130
