"""What every RAP command-line entry point shares: one-line errors, exit codes, logging.

    cli = typer.Typer(add_completion=False, help=__doc__)

    @cli.command()
    def main(plan: Path, log_level: str = "INFO") -> None:
        setup_logging(log_level)                      # EntryError on a bad level
        ...
        raise fail(f"{where}: what is wrong - how to fix it")

    if __name__ == "__main__":
        run_cli(cli)

A mistake in the arguments or an input file is reported as one line on stderr,
``error: file:line:col: what - how to fix`` (or ``error: what - how to fix``), with exit
code 2; never a traceback. Exit code 1 means the run itself failed (a loop that did not
close, a spec found false), 0 success, 130 interrupted.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rap_schemas import keys
from rap_schemas.plan import ENDPOINT
from typer.exceptions import TyperException

__all__ = [
    "USAGE",
    "EntryError",
    "LogFileOpt",
    "LogRedisOpt",
    "MetricsOpt",
    "check_endpoints",
    "check_system",
    "fail",
    "guard",
    "leaf",
    "log_level",
    "run_cli",
    "setup_logging",
]

USAGE = 2
"""Exit code of bad usage or unreadable input."""

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

# the options every RAP service takes for its metrics and structured logs
MetricsOpt = Annotated[
    str | None,
    typer.Option(metavar="HOST:PORT", help="Serve Prometheus metrics on http://HOST:PORT/metrics."),
]
LogFileOpt = Annotated[
    Path | None, typer.Option(help="Also log JSON lines to this file (rotated, bounded).")
]
LogRedisOpt = Annotated[
    str | None,
    typer.Option(metavar="URL", help="Also log to the Redis stream rap:<system>:log."),
]


class EntryError(Exception):
    """Ends a command with ``error: <message>`` and exit ``code``."""

    def __init__(self, message: str, code: int = USAGE) -> None:
        super().__init__(message)
        self.message = message
        self.code = code


def fail(message: str, code: int = USAGE) -> EntryError:
    """``raise fail("plan.yaml:3:5: ... - ...")``."""
    return EntryError(message, code)


def log_level(text: str, option: str = "--log-level") -> int:
    """A logging level from its name, or :class:`EntryError`."""
    level = logging.getLevelNamesMapping().get(text.upper())
    if level is None:
        raise fail(f"{option} {text!r} is not a logging level - use DEBUG, INFO, WARNING or ERROR")
    return level


def setup_logging(level: str, option: str = "--log-level") -> None:
    """Configure the root logger on stderr (entry points only; libraries never do)."""
    logging.basicConfig(level=log_level(level, option), stream=sys.stderr, format=LOG_FORMAT)


def check_system(system: str, option: str = "--system") -> str:
    try:
        keys.system_pattern(system)
    except keys.KeyError_ as exc:
        raise fail(f"{option}: {exc}") from None
    return system


def check_endpoints(option: str, endpoints: Iterable[str] | None) -> list[str]:
    """Zenoh endpoints given on the command line, or :class:`EntryError` naming the bad one."""
    out = list(endpoints or ())
    for endpoint in out:
        if not ENDPOINT.fullmatch(endpoint):
            raise fail(
                f"{option} {endpoint!r} is not a Zenoh endpoint - write "
                "'<protocol>/<address>', e.g. 'tcp/127.0.0.1:7447'"
            )
    return out


def guard(errors: tuple[type[Exception], ...], code: int = USAGE) -> Callable[[Any], Any]:
    """Decorate a command so that ``errors`` (exceptions whose message already says what
    is wrong and how to fix it) end it as :class:`EntryError` lines."""

    def wrap(fn: Callable[..., Any]) -> Callable[..., Any]:
        import functools

        @functools.wraps(fn)
        def inner(*args: Any, **kwargs: Any) -> Any:
            try:
                return fn(*args, **kwargs)
            except errors as exc:
                raise fail(str(exc), code) from None

        return inner

    return wrap


def leaf(exc: BaseException) -> BaseException:
    """The one exception inside nested single-member exception groups (task groups wrap
    a failure that ends them), else ``exc`` itself."""
    while isinstance(exc, BaseExceptionGroup) and len(exc.exceptions) == 1:
        exc = exc.exceptions[0]
    return exc


def _say(message: str) -> None:
    sys.stderr.write(f"error: {message}\n")
    sys.stderr.flush()


def run_cli(
    app: typer.Typer, argv: Sequence[str] | None = None, prog: str | None = None
) -> NoReturn:
    """Run ``app`` as a program: usage mistakes and :class:`EntryError` become one
    ``error:`` line and their exit code (2 for usage), never a traceback."""
    command = typer.main.get_command(app)
    name = prog or _prog_name()
    try:
        rv = command.main(args=argv, prog_name=name, standalone_mode=False)
    except EntryError as exc:
        _say(exc.message)
        sys.exit(exc.code)
    except TyperException as exc:  # click's usage errors (unknown option, bad value, ...)
        _say(f"{exc.format_message()} - see '{name} --help'")
        sys.exit(getattr(exc, "exit_code", USAGE) or USAGE)
    except KeyboardInterrupt:
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)


def _prog_name() -> str:
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None and spec.name:
        return f"python -m {spec.name.removesuffix('.__main__')}"
    return sys.argv[0].rsplit("/", 1)[-1]
