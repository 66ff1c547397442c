"""``rap certs`` and mutual TLS on the fabric: the CA signs one certificate per identity
(its common name the identity, a compute node's subjectAltNames the hosts it is reached
at), existing files are kept, and real Zenoh sessions configured from the generated
router and client configs link over ``tls/`` only with a certificate of the model's CA."""

from __future__ import annotations

import ipaddress
import json
import stat
from pathlib import Path

import anyio
import pytest
import typer
from cryptography import x509
from cryptography.x509.oid import NameOID
from rap_cli.app import app
from rap_cli.certs_cli import CertsError, write_certs
from rap_cli.deploy import TlsFiles, client_config, router_config
from rap_cli.reach import open_fabric, resolve
from rap_schemas import DeploymentPlan, load_plan
from rap_sdk import FabricError, ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port, node_overlay
from typer.testing import CliRunner

MODEL = """\
system: sec
compute_nodes:
  a:
    address: 10.1.2.3
    listen: ["tcp/a:{port}", "tcp/a-host.example:{port}"]
  b:
    connect: ["tcp/a:{port}"]
fabric:
  tls: true
  operators: [alice]
"""


def _model(folder: Path, port: int = 7447) -> Path:
    path = folder / "model.yaml"
    path.write_text(MODEL.format(port=port))
    return path


def _plan(path: Path) -> DeploymentPlan:
    return load_plan(path).plan


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def _sans(cert: x509.Certificate) -> set[str]:
    ext = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return {*ext.get_values_for_type(x509.DNSName)} | {
        str(ip) for ip in ext.get_values_for_type(x509.IPAddress)
    }


def test_the_ca_signs_one_certificate_per_identity(tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    written = write_certs(_plan(_model(tmp_path)), certs, days=30)
    names = sorted(p.name for p in written)
    # the routers, the processes rap up runs (knowledge and the manager on a), operators
    roles = {
        "a": "router",
        "b": "router",
        "a.knowledge": "process",
        "a.manager": "process",
        "alice": "operator",
    }
    assert names == sorted(f"{n}{ext}" for n in ("ca", *roles) for ext in (".pem", ".key"))
    ca = _cert(certs / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name, role in roles.items():
        cert = _cert(certs / f"{name}.pem")
        cert.verify_directly_issued_by(ca)  # raises when the CA did not sign it
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        ou = cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)
        assert ou[0].value == role
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        days = (cert.not_valid_after_utc - cert.not_valid_before_utc).days
        assert 29 <= days <= 30
        # the private key matches the certificate, and only its owner may read it
        key = (certs / f"{name}.key").read_bytes()
        from cryptography.hazmat.primitives.serialization import load_pem_private_key

        assert load_pem_private_key(key, None).public_key() == cert.public_key()
        assert stat.S_IMODE((certs / f"{name}.key").stat().st_mode) == 0o600
    assert stat.S_IMODE((certs / "ca.key").stat().st_mode) == 0o600
    # a compute node: its address, its listen hosts, its name, loopback, compose's name
    assert _sans(_cert(certs / "a.pem")) == {
        "a",
        "10.1.2.3",
        "a-host.example",
        "localhost",
        "127.0.0.1",
        "router",
    }
    assert _sans(_cert(certs / "b.pem")) == {"b", "localhost", "127.0.0.1", "router"}
    ip = _cert(certs / "a.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName)
    assert ipaddress.ip_address("10.1.2.3") in ip.value.get_values_for_type(x509.IPAddress)
    # an operator: a common name only
    with pytest.raises(x509.ExtensionNotFound):
        _cert(certs / "alice.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName)


def test_existing_files_are_kept_without_force(tmp_path: Path) -> None:
    plan = _plan(_model(tmp_path))
    certs = tmp_path / "certs"
    write_certs(plan, certs)
    before = (certs / "a.pem").read_bytes()
    with pytest.raises(CertsError, match=r"ca\.pem, ca\.key, a\.pem.*--force"):
        write_certs(plan, certs)
    assert (certs / "a.pem").read_bytes() == before
    write_certs(plan, certs, force=True)
    assert (certs / "a.pem").read_bytes() != before
    _cert(certs / "a.pem").verify_directly_issued_by(_cert(certs / "ca.pem"))


def test_an_identity_named_twice_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "model.yaml"
    path.write_text("system: s\ncompute_nodes: {a: {}}\nfabric: {operators: [a]}\n")
    with pytest.raises(CertsError, match="'a' is also a compute node"):
        write_certs(_plan(path), tmp_path / "certs")


def test_rap_certs_command(tmp_path: Path) -> None:
    model = _model(tmp_path)
    runner = CliRunner()
    first = runner.invoke(app, ["certs", str(model), "--days", "10", "--address", "b=192.0.2.7"])
    assert first.exit_code == 0, first.output
    assert "robot" not in first.output
    assert "a, b, a.knowledge, a.manager, alice" in first.output
    assert "192.0.2.7" in _sans(_cert(tmp_path / "certs" / "b.pem"))
    again = runner.invoke(app, ["certs", str(model)])
    assert again.exit_code == 2
    assert "rap: error:" in again.output
    assert "--force" in again.output
    forced = runner.invoke(app, ["certs", str(model), "--force", "-o", str(tmp_path / "o")])
    assert forced.exit_code == 0, forced.output
    assert (tmp_path / "o" / "alice.key").is_file()
    bad = runner.invoke(app, ["certs", str(model), "-o", str(tmp_path / "x"), "--days", "0"])
    assert bad.exit_code == 2
    assert "--days 0" in bad.output


def test_router_config_goes_over_tls_with_the_nodes_certificate(tmp_path: Path) -> None:
    plan = _plan(_model(tmp_path))
    files = TlsFiles.of(tmp_path / "certs", "b")
    conf = router_config(plan, "b", local=["tcp/127.0.0.1:9000"], tls=files)
    # its own clients: on loopback, over TLS too (each presents its own certificate)
    assert conf["listen"]["endpoints"] == ["tls/127.0.0.1:9000"]
    assert conf["connect"]["endpoints"] == ["tls/10.1.2.3:7447"]  # a resolved, over TLS
    tls = conf["transport"]["link"]["tls"]
    assert tls["enable_mtls"] is True
    assert tls["verify_name_on_connect"] is True
    assert tls["connect_certificate"] == tls["listen_certificate"] == files.certificate
    assert tls["root_ca_certificate"] == files.ca
    a = router_config(plan, "a", local=[], addresses={"a": "127.0.0.1"}, tls=files)
    assert a["listen"]["endpoints"] == ["tls/127.0.0.1:7447", "tls/a-host.example:7447"]
    with pytest.raises(ValueError, match=r"fabric\.tls"):
        router_config(plan, "a", local=[])
    # a model without tls: as before, no tls block
    plain = tmp_path / "plain.yaml"
    plain.write_text("system: s\ncompute_nodes: {a: {listen: ['tcp/a:7447']}}\n")
    conf = router_config(_plan(plain), "a", local=[], tls=files)
    assert conf["listen"]["endpoints"] == ["tcp/a:7447"]
    assert "tls" not in conf["transport"]["link"]


def _session(conf: dict[str, object]) -> ZenohFabric:
    """A session as a RAP process opens it from a generated config file."""
    return ZenohFabric(node_overlay(ZenohConfig(), json.dumps(conf)))


@pytest.mark.anyio
@pytest.mark.zenoh
async def test_sessions_link_over_mutual_tls_only_with_the_models_ca(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for env in ("RAP_AS", "RAP_CERTS", "RAP_ZENOH_CONFIG"):
        monkeypatch.delenv(env, raising=False)
    port = free_port()
    plan = _plan(_model(tmp_path, port))
    certs, other = tmp_path / "certs", tmp_path / "other"
    write_certs(plan, certs)
    write_certs(plan, other)  # the same identities under another CA
    # as bound on this machine: the model's tcp/a:PORT on loopback, over TLS
    router = router_config(
        plan, "a", local=[], listen=[f"tcp/127.0.0.1:{port}"], tls=TlsFiles.of(certs, "a")
    )
    endpoint = router["listen"]["endpoints"][0]
    assert endpoint.startswith("tls/127.0.0.1:")
    async with _session(router) as edge:
        sub = edge.subscribe("rap/sec/data/probe")
        # an operator with a certificate of the model's CA gets through
        async with _session(client_config(endpoint, TlsFiles.of(certs, "alice"))) as alice:
            with anyio.fail_after(10):
                while True:  # until the subscription has reached the operator's session
                    await alice.publish("rap/sec/data/probe", b"hello")
                    with anyio.move_on_after(0.2):
                        sample = await sub.get()
                        break
        assert sample.payload == b"hello"
        # the same name under another CA: the router refuses the link (and the other CA
        # does not vouch for the router either)
        with pytest.raises(FabricError, match="Unable to connect"):
            async with _session(client_config(endpoint, TlsFiles.of(other, "alice"))):
                pass
        # trusting the right CA but presenting another CA's certificate: refused (mTLS)
        forged = TlsFiles(
            ca=str(certs / "ca.pem"),
            certificate=str(other / "alice.pem"),
            private_key=str(other / "alice.key"),
        )
        with pytest.raises(FabricError, match="Unable to connect"):
            async with _session(client_config(endpoint, forged)):
                pass
        # no certificate at all: refused
        bare = client_config(endpoint, TlsFiles.of(certs, "alice"))
        link = bare["transport"]["link"]["tls"]
        del link["connect_certificate"], link["connect_private_key"]
        raw = ZenohConfig(mode="client", listen=[], connect=[endpoint], extra=bare)
        with pytest.raises(FabricError, match="Unable to connect"):
            async with ZenohFabric(raw):
                pass
        # a RAP process given such a config without an identity says what to set
        with pytest.raises(FabricError, match="RAP_AS=<identity> and RAP_CERTS"):
            _session(bare)
        # the operate verbs' way in (rap_cli.reach): --as NAME, --certs DIR
        reach = resolve(None, "sec", [endpoint], certs=certs, identity="alice")
        assert reach.tls == TlsFiles.of(certs.resolve(), "alice")
        async with open_fabric(reach) as op:
            with anyio.fail_after(10):
                while True:
                    await op.publish("rap/sec/data/probe", b"operator")
                    with anyio.move_on_after(0.2):
                        if (await sub.get()).payload == b"operator":
                            break
        with pytest.raises(typer.Exit) as no_identity:
            resolve(None, "sec", [endpoint], certs=certs)
        assert no_identity.value.exit_code == 2
        with pytest.raises(typer.Exit) as unknown:
            resolve(None, "sec", [endpoint], certs=certs, identity="mallory")
        assert unknown.value.exit_code == 2
        # and the router still serves the right ones
        async with _session(client_config(endpoint, TlsFiles.of(certs, "b"))) as b:
            with anyio.fail_after(10):
                while True:
                    await b.publish("rap/sec/data/probe", b"again")
                    with anyio.move_on_after(0.2):
                        if (await sub.get()).payload == b"again":
                            break
