"""``rap certs``: the certificates of a model's identities, for Zenoh links with mutual TLS.

    rap certs model.yaml                 # <model folder>/certs: ca.pem/.key, <name>.pem/.key
    rap certs model.yaml -o secrets/ --days 90 --force

One certificate authority (``ca.pem``, its key ``ca.key``) signs one certificate per
identity: each compute node (``<node>.pem``, ``<node>.key``), which its router presents
on every TLS link; each RAP process of a node (``<node>.<process>``: ``edge.runner``,
``edge.knowledge``, ...), which it presents to its router; and each of the model's
``fabric.operators``, which an operator's own session presents. A certificate's common
name is its identity (Zenoh's access control matches it: ``cert_common_names``; what
each may do is derived from the model, ``rap_cli.acl``), its organizational unit its
role (``router``, ``process``, ``operator``). A compute node's certificate names, as
subjectAltNames, the hosts it is reached at: its ``address``, the hosts of its ``listen``
endpoints, its own name, ``localhost`` and ``127.0.0.1`` (``rap up --all`` runs every
node on loopback), ``router`` (its service name in the node's compose file) and any
``--address NODE=HOST``. Keys are EC P-256 (PKCS#8 PEM, mode
0600). ``rap up`` reads them when the model says ``fabric: {tls: true}``.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rap_schemas import DeploymentPlan

from .cli import usage

if TYPE_CHECKING:
    from cryptography import x509

__all__ = [
    "CA",
    "LOOPBACK_NAMES",
    "ROLES",
    "CertsError",
    "Identity",
    "identities",
    "register",
    "write_certs",
]

ROLES = {"compute node": "router", "process": "process", "operator": "operator"}
"""The organizational unit (OU) of each kind of identity's certificate."""
CA = "ca"
"""The certificate authority's file stem: ``ca.pem``, ``ca.key``."""
LOOPBACK_NAMES = ("localhost", "127.0.0.1")
"""Names every compute node's certificate carries, for nodes run on one machine."""
COMPOSE_ROUTER = "router"
"""The router's service name in a node's compose file, where its processes reach it."""
_HOST = re.compile(r"^[a-z][a-z0-9+\-]*/(?P<host>\[[^\]]*\]|[^:/\[]+)")
_WILDCARD = {"0.0.0.0", "::", ""}


class CertsError(Exception):
    """The certificates cannot be made as asked (the message says what to do)."""


@dataclass(frozen=True, slots=True)
class Identity:
    """One certificate to make: its common name and the hosts it is valid for."""

    name: str
    kind: str
    """``compute node`` (its router), ``process`` (a RAP process of a node) or
    ``operator``; the certificate carries it as its organizational unit, which is how
    a receiver tells an operator's signature (``rap_sdk.identity``)."""
    hosts: tuple[str, ...] = ()
    """subjectAltNames: DNS names and IP addresses."""


def _endpoint_host(endpoint: str) -> str:
    m = _HOST.match(endpoint)
    return m["host"].strip("[]") if m is not None else ""


def identities(plan: DeploymentPlan, addresses: Mapping[str, str] | None = None) -> list[Identity]:
    """The identities of ``plan``: its compute nodes (with the hosts each is reached at,
    ``addresses`` adding one per node) and its operators; ``CertsError`` when a name is
    given twice or is the CA's."""
    out: list[Identity] = []
    seen: dict[str, str] = {}
    for name, spec in plan.compute_nodes.items():
        hosts = [name]
        if spec.address:
            hosts.append(spec.address)
        hosts += [_endpoint_host(e) for e in spec.listen]
        if name in (addresses or {}):
            hosts.append((addresses or {})[name])
        hosts += LOOPBACK_NAMES
        hosts.append(COMPOSE_ROUTER)
        clean = [h.strip("[]") for h in hosts]
        out.append(
            Identity(
                name, "compute node", tuple(dict.fromkeys(h for h in clean if h not in _WILDCARD))
            )
        )
    from .acl import process_grants

    out += [
        Identity(g.identity, "process")
        for g in process_grants(plan).values()
        if g.kind not in ("router", "operator")
    ]
    out += [Identity(name, "operator") for name in plan.fabric.operators]
    for ident in out:
        if ident.name == CA:
            raise CertsError(
                f"{ident.kind} {CA!r}: {CA}.pem is the certificate authority's file - rename it"
            )
        if ident.name in seen:
            raise CertsError(
                f"{ident.kind} {ident.name!r} is also a {seen[ident.name]}: one certificate "
                "per identity - rename one of them"
            )
        seen[ident.name] = ident.kind
    return out


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` readable by its owner only (mode 0600)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        os.fchmod(f.fileno(), 0o600)  # an existing file (--force) keeps no wider mode
        f.write(data)


def _san(host: str) -> x509.GeneralName:
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def write_certs(
    plan: DeploymentPlan,
    folder: Path,
    *,
    days: int = 365,
    force: bool = False,
    addresses: Mapping[str, str] | None = None,
) -> list[Path]:
    """Make the CA and a certificate for each identity of ``plan`` in ``folder``; the
    files written, the CA's first. ``CertsError`` when a file is there and not
    ``force``, or a name is unusable."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if days < 1:
        raise CertsError(f"--days {days}: a certificate must be valid for at least 1 day")
    people = identities(plan, addresses)
    stems = [CA, *(i.name for i in people)]
    files = [folder / f"{s}{ext}" for s in stems for ext in (".pem", ".key")]
    there = [f.name for f in files if f.exists()]
    if there and not force:
        raise CertsError(
            f"{folder}: {', '.join(there)} already there - give --force to make every "
            "certificate again (under a new CA: the old ones stop being trusted), or "
            "another folder with -o"
        )
    folder.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC)
    start, end = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)
    pem = serialization.Encoding.PEM

    def key_bytes(key: ec.EllipticCurvePrivateKey) -> bytes:
        return key.private_bytes(
            pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"rap {plan.system}"),
            x509.NameAttribute(NameOID.COMMON_NAME, f"rap {plan.system} CA"),
        ]
    )
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False)
        .sign(ca_key, hashes.SHA256())
    )
    written = [folder / f"{CA}.pem", folder / f"{CA}.key"]
    written[0].write_bytes(ca_cert.public_bytes(pem))
    _write_private(written[1], key_bytes(ca_key))
    aki = x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key())
    for ident in people:
        key = ec.generate_private_key(ec.SECP256R1())
        subject = x509.Name(
            [
                x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"rap {plan.system}"),
                x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, ROLES[ident.kind]),
                x509.NameAttribute(NameOID.COMMON_NAME, ident.name),
            ]
        )
        builder = (
            x509.CertificateBuilder()
            .subject_name(subject)
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(start)
            .not_valid_after(end)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(
                    digital_signature=True,
                    content_commitment=False,
                    key_encipherment=False,
                    data_encipherment=False,
                    key_agreement=False,
                    key_cert_sign=False,
                    crl_sign=False,
                    encipher_only=False,
                    decipher_only=False,
                ),
                critical=True,
            )
            .add_extension(
                x509.ExtendedKeyUsage(
                    [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
                ),
                critical=False,
            )
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
            .add_extension(aki, False)
        )
        if ident.hosts:
            names = [_san(h) for h in ident.hosts]
            builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
        cert = builder.sign(ca_key, hashes.SHA256())
        cert_path, key_path = folder / f"{ident.name}.pem", folder / f"{ident.name}.key"
        cert_path.write_bytes(cert.public_bytes(pem))
        _write_private(key_path, key_bytes(key))
        written += [cert_path, key_path]
    return written


def _parse_addresses(plan: DeploymentPlan, given: Sequence[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in given:
        node, sep, host = item.partition("=")
        node, host = node.strip(), host.strip()
        if not sep or not node or not host:
            usage(f"--address {item!r} is not NODE=HOST - write e.g. --address edge=10.0.0.2")
        if node not in plan.compute_nodes:
            usage(
                f"--address {item!r}: {node!r} is not a compute node of the model - use one "
                f"of: {', '.join(plan.compute_nodes)}"
            )
        out[node] = host
    return out


def certs_cmd(
    model: Annotated[
        Path,
        typer.Argument(
            help="The system model (model.yaml, or the folder holding it).",
            show_default=False,
            metavar="MODEL",
        ),
    ],
    output: Annotated[
        Path | None,
        typer.Option(
            "--output",
            "-o",
            help="The folder to write (default: `<model folder>/certs`).",
            show_default=False,
        ),
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Replace the files that are there already.")
    ] = False,
    days: Annotated[int, typer.Option("--days", help="Days the certificates are valid.")] = 365,
    address: Annotated[
        list[str] | None,
        typer.Option(
            "--address",
            help="NODE=HOST: one more host name or address compute node NODE's certificate "
            "is valid for (as given to rap up --address), repeatable.",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Make a certificate authority and one certificate per identity of a model: each
    compute node (its router presents it on TLS links) and each of `fabric.operators`.
    Each certificate's common name is the identity; a compute node's also names the hosts
    it is reached at (its address, its listen hosts, its name, localhost, 127.0.0.1).
    Files: `ca.pem`, `ca.key`, `<name>.pem`, `<name>.key` (keys mode 0600; keep `ca.key`
    and each node's key secret, and copy to each machine only its own). Existing files
    are kept unless --force. `rap up` uses them when the model says `fabric: {tls: true}`.

    Example: `rap certs examples/lidar_occlusion/model.yaml -o certs/ --days 90`"""
    from .up import _load

    file, doc = _load(model)
    folder = output if output is not None else file.parent / "certs"
    addresses = _parse_addresses(doc.plan, address or [])
    try:
        written = write_certs(doc.plan, folder, days=days, force=force, addresses=addresses)
    except CertsError as exc:
        usage(str(exc))
    except OSError as exc:
        usage(f"{folder}: cannot write it ({exc.strerror}) - choose another folder with -o")
    names = [p.stem for p in written if p.suffix == ".pem" and p.stem != CA]
    typer.echo(
        f"wrote {folder}: the CA ({CA}.pem, {CA}.key) and {len(names)} certificate(s): "
        f"{', '.join(names) or '-'}; valid {days} day(s)"
    )
    if not doc.plan.fabric.tls:
        typer.echo(f"note: {file} does not say fabric: {{tls: true}} - rap up does not use them")


def register(app: typer.Typer) -> None:
    """Add ``rap certs`` to ``app``."""
    app.command("certs")(certs_cmd)
