"""``rap models list|pin|unpin|rollback``: the model store of a running system's knowledge
service (versions of named binary models, ``rap_sdk.KnowledgeClient.put_model``), from
any machine that reaches one of its routers.

    rap models list model.yaml occlusion            # versions, sha256, size, created, tags
    rap models pin model.yaml occlusion 2           # version 2 is in force from now on
    rap models rollback model.yaml occlusion        # pin the version before the one in force
    rap models unpin model.yaml occlusion           # the latest is in force again

The fabric is reached as the operate verbs reach it (:mod:`rap_cli.reach`): ``--connect``,
else ``RAP_ZENOH_CONFIG``, else the routers of the ``rap up`` that runs the model. With
``fabric: {tls: true}`` the knowledge service takes model requests only signed, by an
operator or by a process the model grants the model (``models:``): each request is signed
as ``--as`` (or ``RAP_AS``), one of ``fabric.operators``, with its certificate in
``--certs`` (or ``RAP_CERTS``, or ``<model folder>/certs``). The service audits every
request (``rap logs --audit``): who, what, and what came of it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import anyio
import msgspec
import typer

from .cli import OK, failed, usage
from .reach import AsOpt, CertsOpt, ConnectOpt, Reach, RunDirOpt, open_fabric, resolve, signer_of

if TYPE_CHECKING:
    from rap_schemas import ModelMeta
    from rap_sdk import KnowledgeClient
    from rap_sdk.identity import Signer

__all__ = ["models_app", "register", "table"]

T = TypeVar("T")

models_app = typer.Typer(
    help="The model store of a running system's knowledge service: list a model's "
    "versions, pin one, unpin, roll back.",
    no_args_is_help=True,
)

ModelArg = Annotated[
    Path,
    typer.Argument(
        help="The system model (model.yaml, or its folder): its system, the routers of the "
        "`rap up` that runs it, its certificates.",
        show_default=False,
        metavar="MODEL",
    ),
]
NameArg = Annotated[
    str,
    typer.Argument(
        help="The model's name in the store (e.g. occlusion).", show_default=False, metavar="NAME"
    ),
]
TimeoutOpt = Annotated[
    float, typer.Option("--timeout", help="Seconds to wait for the knowledge service.")
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")]


def _check_name(name: str) -> None:
    from rap_schemas import MODELS_PREFIX, keys

    try:
        keys.kb("x", f"{MODELS_PREFIX}/{name}")
    except keys.KeyError_ as exc:
        usage(f"{name!r} is not a model name: {exc}")


def _reach(
    model: Path,
    connect: list[str] | None,
    run_dir: Path | None,
    certs: Path | None,
    identity: str | None,
) -> tuple[Reach, Signer | None]:
    """The fabric and the identity requests are signed as; a usage error when the model
    has TLS and no identity is named (the service would refuse every request)."""
    if not model.exists():
        usage(f"{model}: no such file - give the system model (model.yaml, or its folder)")
    reach = resolve(model, None, connect, run_dir, certs=certs, identity=identity)
    signer = signer_of(model, certs, identity)
    plan = reach.plan
    if signer is None and plan is not None and plan.fabric.tls:
        ops = ", ".join(plan.fabric.operators) or "none yet: add fabric.operators, rap certs"
        usage(
            "the model has fabric.tls: its knowledge service takes model requests only "
            f"signed - give --as NAME (one of fabric.operators: {ops}) and --certs DIR "
            "(default: <model folder>/certs), or set RAP_AS and RAP_CERTS"
        )
    return reach, signer


async def _ask(
    reach: Reach,
    signer: Signer | None,
    timeout: float,
    op: Callable[[KnowledgeClient], Awaitable[T]],
) -> T | Exception:
    """``op`` on a knowledge client of the system; its :class:`KnowledgeError` returned
    (to be reported outside the event loop)."""
    from rap_sdk import KnowledgeClient
    from rap_sdk.knowledge import KnowledgeError

    async with (
        open_fabric(reach) as fabric,
        KnowledgeClient(
            fabric=fabric, system=reach.system, writer="rap-models", timeout=timeout, signer=signer
        ) as kb,
    ):
        try:
            return await op(kb)
        except KnowledgeError as exc:
            return exc


def _run(
    what: str,
    name: str,
    where: tuple[Path, list[str] | None, Path | None, Path | None, str | None],
    timeout: float,
    op: Callable[[KnowledgeClient], Awaitable[T]],
) -> tuple[Reach, T]:
    if timeout <= 0:
        usage(f"--timeout {timeout:g}: give a number of seconds > 0")
    reach, signer = _reach(*where)
    got = anyio.run(_ask, reach, signer, timeout, op)
    if isinstance(got, Exception):
        hint = ""
        if getattr(got, "code", "") == "not-found":
            hint = f" - `rap models list {where[0]} {name}` shows its versions"
        failed(f"{what}: {got}{hint}")
    return reach, got


def _size(n: int) -> str:
    size = float(n)
    for unit in ("B", "KiB", "MiB"):
        if size < 1024:
            return f"{n} B" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{size:.1f} GiB"


def _when(ns: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(ns / 1e9))


def table(versions: list[ModelMeta], pinned: int | None) -> str:
    """Versions as ``rap models list`` prints them: version, sha256 prefix, size,
    created (UTC), tags, and which is in force (the pinned one, else the latest)."""
    head = ("VERSION", "SHA256", "SIZE", "CREATED", "TAGS", "")
    rows = [head]
    latest = versions[-1].version if versions else None
    for m in versions:
        state = ""
        if m.version == pinned:
            state = "pinned (in force)"
        elif pinned is None and m.version == latest:
            state = "latest (in force)"
        tags = ",".join(f"{k}={v}" for k, v in sorted(m.tags.items())) or "-"
        rows.append((str(m.version), m.sha256[:12], _size(m.size), _when(m.created), tags, state))
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    return "\n".join(
        "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows
    )


@models_app.command("list")
def list_(
    model: ModelArg,
    name: NameArg,
    as_json: JsonOpt = False,
    timeout: TimeoutOpt = 5.0,
    connect: ConnectOpt = None,
    run_dir: RunDirOpt = None,
    certs: CertsOpt = None,
    identity: AsOpt = None,
) -> None:
    """A model's versions in the store: version, sha256 (its first 12 digits), size,
    created, tags, and which is in force (the pinned one, else the latest). Exit 1 when
    the store has none.

    Example: `rap models list model.yaml occlusion --as ops`
    """
    _check_name(name)
    where = (model, connect, run_dir, certs, identity)
    reach, (versions, pinned) = _run(
        f"list {name}", name, where, timeout, lambda kb: kb.list_models(name)
    )
    if as_json:
        data: dict[str, Any] = {
            "name": name,
            "pinned": pinned,
            "versions": [msgspec.to_builtins(m) for m in versions],
        }
        typer.echo(json.dumps(data, indent=2))
    if not versions:
        failed(
            f"no model {name!r} in the store of system {reach.system!r} - put one first "
            "(KnowledgeClient.put_model), or check the name"
        )
    if not as_json:
        force = (
            f"version {pinned} (pinned)"
            if pinned is not None
            else f"the latest, version {versions[-1].version} (none pinned)"
        )
        typer.echo(f"model {name}: {len(versions)} version(s); in force: {force}")
        typer.echo(table(versions, pinned))
    raise typer.Exit(OK)


@models_app.command("pin")
def pin(
    model: ModelArg,
    name: NameArg,
    version: Annotated[
        int,
        typer.Argument(help="The version to put in force.", show_default=False, metavar="VERSION"),
    ],
    timeout: TimeoutOpt = 5.0,
    connect: ConnectOpt = None,
    run_dir: RunDirOpt = None,
    certs: CertsOpt = None,
    identity: AsOpt = None,
) -> None:
    """Pin a version: it is the one `get_model(name)` returns, whatever is put later,
    until another is pinned, or `rap models unpin`.

    Example: `rap models pin model.yaml occlusion 2 --as ops`
    """
    _check_name(name)
    if version < 1:
        usage(f"version {version}: versions count from 1 (rap models list shows them)")
    where = (model, connect, run_dir, certs, identity)
    _, pinned = _run(
        f"pin {name} {version}", name, where, timeout, lambda kb: kb.pin_model(name, version)
    )
    typer.echo(f"model {name}: version {pinned} pinned (in force)")


@models_app.command("unpin")
def unpin(
    model: ModelArg,
    name: NameArg,
    timeout: TimeoutOpt = 5.0,
    connect: ConnectOpt = None,
    run_dir: RunDirOpt = None,
    certs: CertsOpt = None,
    identity: AsOpt = None,
) -> None:
    """Unpin a model: its latest version is in force again.

    Example: `rap models unpin model.yaml occlusion --as ops`
    """
    _check_name(name)
    where = (model, connect, run_dir, certs, identity)
    _run(f"unpin {name}", name, where, timeout, lambda kb: kb.pin_model(name, None))
    typer.echo(f"model {name}: unpinned, the latest version is in force")


@models_app.command("rollback")
def rollback(
    model: ModelArg,
    name: NameArg,
    timeout: TimeoutOpt = 5.0,
    connect: ConnectOpt = None,
    run_dir: RunDirOpt = None,
    certs: CertsOpt = None,
    identity: AsOpt = None,
) -> None:
    """Roll a model back: pin the version before the one in force. Exit 1 when there is
    none older.

    Example: `rap models rollback model.yaml occlusion --as ops`
    """
    _check_name(name)
    where = (model, connect, run_dir, certs, identity)
    _, pinned = _run(f"rollback {name}", name, where, timeout, lambda kb: kb.rollback_model(name))
    typer.echo(f"model {name}: rolled back, version {pinned} pinned (in force)")


def register(app: typer.Typer) -> None:
    """Add ``rap models`` to ``app``."""
    app.add_typer(models_app, name="models")
