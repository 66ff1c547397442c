"""How the operate verbs (``rap status``, ``rap topic echo``, ``rap record``, ...) reach a
running system's fabric, from this machine or any other that reaches a router.

Each verb takes the same options:

- ``--system NAME``: the system (default: the model's, else ``RAP_SYSTEM``);
- ``--connect ENDPOINT`` (repeatable): a Zenoh router to go through;
- ``--model MODEL`` (default: ``./model.yaml`` when there is one): the system and, when no
  endpoint is given, the routers of the compute nodes ``rap up`` runs from it;
- ``--run-dir``: where that ``rap up`` keeps its state.

Without ``--connect``, ``RAP_ZENOH_CONFIG`` (a Zenoh client config, as inside a
container) says where the fabric is; else the ``rap up`` of the model does.

A router reached over TLS (``--connect tls/HOST:PORT``, a model with ``fabric: {tls:
true}``) wants a certificate of the model's CA: ``--as NAME`` (an identity ``rap certs``
made: one of ``fabric.operators``) and ``--certs DIR`` (default: ``<model
folder>/certs``), or ``RAP_AS`` and ``RAP_CERTS``. The router of a ``rap up`` on this
machine is reached on its loopback ``tcp/`` endpoint, without one.

The admin verbs (``rap status``, ``rap pause``, ...) also sign each request as that
identity whenever one is named, whatever the endpoint (:meth:`Where.signer`): a
component whose process has identities takes only signed requests, and changes only from
an operator.
"""

from __future__ import annotations

import functools
import inspect
import os
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from .cli import failed, usage

if TYPE_CHECKING:
    from rap_schemas import DeploymentPlan
    from rap_sdk import ZenohFabric
    from rap_sdk.identity import Signer

    from .deploy import TlsFiles

__all__ = [
    "AS_ENV",
    "CERTS_ENV",
    "SYSTEM_ENV",
    "AsOpt",
    "CertsOpt",
    "ConnectOpt",
    "ModelOpt",
    "Reach",
    "RunDirOpt",
    "SystemOpt",
    "Where",
    "find_model",
    "open_fabric",
    "reach_options",
    "resolve",
    "signer_of",
]

SYSTEM_ENV = "RAP_SYSTEM"
CERTS_ENV = "RAP_CERTS"
"""The folder of ``rap certs`` when ``--certs`` is not given."""
AS_ENV = "RAP_AS"
"""The identity to present on TLS links when ``--as`` is not given."""

ModelOpt = Annotated[
    Path | None,
    typer.Option(
        "--model",
        "-m",
        help="The system model (default: ./model.yaml when there is one): its system, and "
        "the routers of the `rap up` that runs it.",
        show_default=False,
    ),
]
SystemOpt = Annotated[
    str | None,
    typer.Option(
        "--system",
        "-s",
        help=f"The system's name (default: the model's, else ${SYSTEM_ENV}).",
        show_default=False,
    ),
]
ConnectOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--connect",
        "-c",
        help="A Zenoh endpoint of the fabric (a router: tcp/HOST:PORT), repeatable.",
        show_default=False,
    ),
]
RunDirOpt = Annotated[
    Path | None,
    typer.Option(
        "--run-dir",
        help="Where the model's `rap up` keeps its state "
        "(default: `<model folder>/.rap/<system>`).",
        show_default=False,
    ),
]


CertsOpt = Annotated[
    Path | None,
    typer.Option(
        "--certs",
        help=f"The certificates `rap certs` wrote, for a tls/ endpoint (default: "
        f"`<model folder>/certs`, else ${CERTS_ENV}).",
        show_default=False,
    ),
]
AsOpt = Annotated[
    str | None,
    typer.Option(
        "--as",
        help=f"The identity whose certificate (in --certs) is presented to a tls/ endpoint: "
        f"one of the model's fabric.operators (default: ${AS_ENV}).",
        show_default=False,
    ),
]


@dataclass(frozen=True)
class Reach:
    """A system, and where its fabric is."""

    system: str
    endpoints: list[str]
    """Routers to connect to (empty: ``RAP_ZENOH_CONFIG`` says)."""
    where: str
    """Said in errors: how the fabric was found."""
    plan: DeploymentPlan | None = field(default=None, repr=False)
    """The model's plan, when one was given or found."""
    tls: TlsFiles | None = None
    """The certificate presented to ``tls/`` endpoints (None: no TLS)."""


@dataclass(frozen=True)
class Where:
    """The reach options of one command line (see :func:`reach_options`)."""

    model: Path | None = None
    system: str | None = None
    connect: list[str] | None = None
    run_dir: Path | None = None
    certs: Path | None = None
    identity: str | None = None

    def resolve(self) -> Reach:
        return resolve(
            self.model,
            self.system,
            self.connect,
            self.run_dir,
            certs=self.certs,
            identity=self.identity,
        )

    def signer(self) -> Signer | None:
        """The identity requests are signed as (see :func:`signer_of`)."""
        return signer_of(self.model, self.certs, self.identity)


_REACH_OPTIONS: tuple[tuple[str, Any], ...] = (
    ("model", ModelOpt),
    ("system", SystemOpt),
    ("connect", ConnectOpt),
    ("run_dir", RunDirOpt),
    ("certs", CertsOpt),
    ("identity", AsOpt),
)


def reach_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Give a typer command the reach options (``--model``, ``--system``, ``--connect``,
    ``--run-dir``, ``--certs``, ``--as``): ``fn`` takes them as one keyword argument,
    ``where`` (a :class:`Where`); its command line lists them after its own."""
    sig = inspect.signature(fn, eval_str=True)
    own = [p for p in sig.parameters.values() if p.name != "where"]
    added = [
        inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None, annotation=ann)
        for name, ann in _REACH_OPTIONS
    ]

    @functools.wraps(fn)
    def command(*args: Any, **kwargs: Any) -> Any:
        where = Where(**{name: kwargs.pop(name, None) for name, _ in _REACH_OPTIONS})
        return fn(*args, where=where, **kwargs)

    params = [*own, *added]
    command.__signature__ = sig.replace(parameters=params)  # type: ignore[attr-defined]
    command.__annotations__ = {p.name: p.annotation for p in params}
    command.__annotations__["return"] = sig.return_annotation
    return command


def find_model(model: Path | None) -> Path | None:
    """The model file ``--model`` names (a folder: its model.yaml), else ./model.yaml
    when there is one."""
    if model is not None:
        return model / "model.yaml" if model.is_dir() else model
    here = Path("model.yaml")
    return here if here.is_file() else None


def resolve(
    model: Path | None,
    system: str | None,
    connect: list[str] | None,
    run_dir: Path | None = None,
    *,
    certs: Path | None = None,
    identity: str | None = None,
) -> Reach:
    """The system and endpoints the options name; a usage error says what to give.
    ``certs``, ``identity``: ``--certs`` and ``--as``, for ``tls/`` endpoints."""
    from rap_sdk.entry import EntryError, check_endpoints

    from .up import STATE_FILE, _load, _running, read_state

    file = find_model(model)
    plan = None
    if file is not None:
        file, doc = _load(file)
        plan = doc.plan
    name = system or (plan.system if plan is not None else None) or os.environ.get(SYSTEM_ENV)
    if not name:
        usage(
            f"which system? give --system NAME, --model MODEL, or set {SYSTEM_ENV} "
            "(or run the command in the folder of the model.yaml)"
        )
    from rap_schemas import keys

    try:
        keys.system_pattern(name)
    except keys.KeyError_ as exc:
        usage(f"--system {name!r}: {exc}")
    endpoints = list(connect or [])
    try:
        check_endpoints("--connect", endpoints)
    except EntryError as exc:
        usage(exc.message)
    if endpoints:
        os.environ.pop("RAP_ZENOH_CONFIG", None)  # --connect says where: no overlay
        tls = _tls(endpoints, file, certs, identity)
        return Reach(name, endpoints, ", ".join(endpoints), plan, tls)
    if os.environ.get("RAP_ZENOH_CONFIG"):
        return Reach(name, [], f"RAP_ZENOH_CONFIG={os.environ['RAP_ZENOH_CONFIG']}", plan)
    if file is None or plan is None:
        usage(
            "where is the fabric? give --connect ENDPOINT (a router, tcp/HOST:PORT), "
            "--model MODEL of a running `rap up`, or set RAP_ZENOH_CONFIG"
        )
    base = (run_dir or (file.parent / ".rap" / plan.system)).resolve()
    for node in plan.compute_nodes:
        state = read_state(base / node / STATE_FILE)
        if _running(state) and state is not None and isinstance(state.get("router"), str):
            endpoints.append(state["router"])
    if not endpoints:
        usage(
            f"no rap up runs {file} (nothing running under {base}) - start it (rap up "
            f"{file} --all) or give --connect ENDPOINT"
        )
    return Reach(name, endpoints, f"the routers of rap up: {', '.join(endpoints)}", plan)


def _tls(
    endpoints: list[str], model: Path | None, certs: Path | None, identity: str | None
) -> TlsFiles | None:
    """The certificate to present to the ``tls/`` ones of ``endpoints`` (None: none is)."""
    from .deploy import TlsFiles

    secure = [e for e in endpoints if e.startswith("tls/")]
    if not secure:
        return None
    name = identity or os.environ.get(AS_ENV)
    if not name:
        usage(
            f"{secure[0]} is a TLS endpoint: present a certificate with --as NAME (an "
            f"operator of the model's fabric.operators, made by rap certs MODEL) or set {AS_ENV}"
        )
    given = certs or (Path(os.environ[CERTS_ENV]) if os.environ.get(CERTS_ENV) else None)
    folder = given or (model.parent / "certs" if model is not None else None)
    if folder is None:
        usage(f"--as {name}: where are the certificates? give --certs DIR or set {CERTS_ENV}")
    files = TlsFiles.of(folder.resolve(), name)
    missing = files.missing()
    if missing:
        usage(
            f"{folder}: no certificate for {name!r} (missing: "
            f"{', '.join(Path(m).name for m in missing)}) - add {name} to the model's "
            "fabric.operators and run rap certs MODEL, or give --certs DIR"
        )
    return files


def signer_of(model: Path | None, certs: Path | None, identity: str | None) -> Signer | None:
    """The identity ``--as`` (else ``RAP_AS``) names, to sign requests with, its files
    in ``--certs`` (else ``RAP_CERTS``, else ``<model folder>/certs``); None when no
    identity is named. A usage error says what is missing."""
    from rap_sdk.identity import IdentityError, load_signer

    name = identity or os.environ.get(AS_ENV)
    if not name:
        return None
    given = certs or (Path(os.environ[CERTS_ENV]) if os.environ.get(CERTS_ENV) else None)
    file = find_model(model)
    folder = given or (file.parent / "certs" if file is not None else None)
    if folder is None:
        usage(f"--as {name}: where are the certificates? give --certs DIR or set {CERTS_ENV}")
    try:
        return load_signer(folder, name)
    except IdentityError as exc:
        usage(f"--as {name}: {exc}")


@asynccontextmanager
async def open_fabric(reach: Reach) -> AsyncIterator[ZenohFabric]:
    """A client session on the fabric ``reach`` names; a clear error when it cannot be
    reached."""
    from rap_sdk import FabricError, ZenohConfig, ZenohFabric

    extra: dict[str, object] = {}
    if reach.tls is not None:
        from .deploy import client_config

        extra["transport"] = client_config("", reach.tls)["transport"]
    conf = ZenohConfig(mode="client", listen=[], connect=reach.endpoints, extra=extra)
    try:
        fabric = ZenohFabric(conf)
        await fabric.__aenter__()
    except FabricError as exc:
        trust = (
            f", and does it trust {reach.tls.certificate} (the same CA, rap certs)?"
            if reach.tls is not None
            else "?"
        )
        failed(
            f"cannot reach the fabric through {reach.where}: {exc} - is its router running "
            f"(rap up){trust}"
        )
    try:
        yield fabric
    finally:
        await fabric.__aexit__(None, None, None)
