"""``python -m trust_checker SPEC``: run a trust spec on a trace file, MQTT, Redis or the
fabric, with inputs from ROS 2 topics over DDS as well.

    python -m trust_checker spec.dsrv --input-file trace.txt      console lines, then exit
    python -m trust_checker spec.dsrv --check                     validate only
    python -m trust_checker spec.dsrv --mqtt 127.0.0.1:1883 [--topics JSON] [--tagged]
    python -m trust_checker spec.dsrv --redis redis://127.0.0.1:6379/0 [--redis-channels JSON]
    python -m trust_checker spec.dsrv --fabric SYSTEM [--connect EP ...] [--listen EP ...]
    python -m trust_checker spec.dsrv --dds 0 [--dds-topics JSON] [--dds-qos 0|1]
    python -m trust_checker new.dsrv --send-swap --fabric SYSTEM --connect EP --as NAME --certs DIR
    python -m trust_checker new.dsrv --send-swap --mqtt HOST:PORT --as NAME --certs DIR
    python -m trust_checker new.dsrv --send-swap --redis URL --as NAME --certs DIR

MQTT connections take a user name (``--mqtt-user``), a password from an environment
variable (``--mqtt-password-env VAR``) or a file (``--mqtt-password-file``), never from
the command line, and TLS (``--mqtt-ca``, and ``--mqtt-cert``/``--mqtt-key`` for a
broker that wants a client certificate); Redis connections the same with ``--redis-*``
(``rediss://`` or ``--redis-tls`` for TLS). With identities (``--certs DIR``, default
``$RAP_CERTS``: the folder ``rap certs`` wrote) the checker takes a new spec, over the
fabric, MQTT or Redis, only when an operator signed it (over Redis, only with
identities); ``--send-swap`` sends one, signed as ``--as NAME`` (default ``$RAP_AS``),
and prints what the checker answered.

A mistake on the command line or in a file (a bad option value, a bad JSON map, a spec
or trace file that is missing or not text, a bad endpoint or system name) is one line on
stderr, ``error: [file:line:col: ]what - how to fix``, and exit code 2. A spec with
errors prints every problem (file:line:col, the text, a hint), then that line, and exits
with code 2 without starting. A trace file prints every tick computed, then, on a
run-time error, the error line: exit code 1 (2 for a value the spec refuses). Live modes
print each output as a console line (``name[tick] = Int(7)``) and run until SIGTERM or
SIGINT, then exit 0.

Live modes publish verdicts (a Bool output turned false, a trigger fired; see
docs/trust_checker.md, "Explanations and triggers") on the fabric, on MQTT
(``--verdict-topic``) and on Redis (``--redis-verdict-channel``, and a stream with
``--redis-verdict-stream``). ``--explain`` also writes each verdict to stderr as one JSON line
(``rap.TrustVerdict``); stdout stays the reference checker's console lines.
"""

from __future__ import annotations

import importlib.util
import logging
import signal
import sys
from collections.abc import AsyncIterator
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import anyio
import typer
from rap_schemas import TrustSpecStatus, keys
from rap_sdk import FabricError, RapError, ZenohConfig, ZenohFabric
from rap_sdk.entry import (
    LogFileOpt,
    LogRedisOpt,
    MetricsOpt,
    check_endpoints,
    check_system,
    fail,
    run_cli,
    setup_logging,
)
from rap_sdk.errors import ConfigError
from rap_sdk.identity import AS_ENV, CERTS_ENV, IdentityError, load_signer, load_verifier
from rap_sdk.logs import LogContext, check_redis_url, open_file_log, publish_logs
from rap_sdk.metrics import TrustCollector, VerdictCounts, check_metrics_option, start_metrics

from .config import (
    ChannelMap,
    DdsConfig,
    DdsTopic,
    FabricConfig,
    FabricInput,
    MqttConfig,
    RedisConfig,
    ServiceConfig,
    TopicMap,
    decode_map,
)
from .console import ConsoleSink, console_lines, verdict_lines
from .engine import SpecRunner
from .errors import EvalError, InputError, SpecError, TextFileError
from .explain import Explainer, to_message
from .io.mqtt import mqtt_credentials
from .io.ports import Sink
from .io.redis import redis_credentials
from .lang import load_spec, read_source
from .lang.ast import Spec
from .service import TrustService, open_service
from .tracefile import load_trace

if TYPE_CHECKING:
    from rap_sdk.identity import Signer, Verifier

__all__ = ["cli", "main"]

cli = typer.Typer(add_completion=False, help=__doc__)
T = TypeVar("T")

log = logging.getLogger(__name__)

_HOW_TO_RUN = (
    "give --input-file FILE, --mqtt HOST:PORT, --redis URL, --fabric SYSTEM or --dds DOMAIN"
)
_MQTT_OPTIONS = (
    ("password_env", "--mqtt-password-env"),
    ("password_file", "--mqtt-password-file"),
    ("username", "--mqtt-user"),
    ("cert", "--mqtt-cert"),
    ("key", "--mqtt-key"),
)
_REDIS_OPTIONS = (
    ("password_env", "--redis-password-env"),
    ("password_file", "--redis-password-file"),
    ("username", "--redis-user"),
    ("cert", "--redis-cert"),
    ("key", "--redis-key"),
    ("url", "--redis"),
)
_EXAMPLES: dict[type, str] = {
    TopicMap: '{"stream": {"topic": "a/b"}}',
    ChannelMap: '{"stream": {"channel": "robot/x"}}',
    FabricInput: '{"stream": {"key": "rap/s/data/x", "field": "f"}}',
    DdsTopic: '{"stream": {"topic": "/robot/x", "type": "std_msgs/msg/Float64"}}',
}


def _mqtt_address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, 1883
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise fail(f"--mqtt {text!r} is not HOST:PORT - write e.g. 127.0.0.1:1883")
    return host, int(port)


@cli.command()
def main(
    spec: Annotated[Path, typer.Argument(metavar="SPEC", help="The spec (.dsrv or .lola).")],
    input_file: Annotated[
        Path | None, typer.Option("--input-file", help="Run on a trace file and exit.")
    ] = None,
    check: Annotated[bool, typer.Option("--check", help="Only validate the spec.")] = False,
    mqtt: Annotated[
        str | None, typer.Option("--mqtt", metavar="HOST:PORT", help="Run on an MQTT broker.")
    ] = None,
    topics: Annotated[
        str | None,
        typer.Option(
            help='MQTT topic map, JSON: {"stream": {"topic": "a/b"}} (default: the stream\'s name).'
        ),
    ] = None,
    tagged: Annotated[
        bool,
        typer.Option("--tagged", help='Publish D5.2 tagged values ({"Int": 42}) (MQTT, Redis).'),
    ] = False,
    spec_topic: Annotated[str, typer.Option(help="MQTT hot-swap topic.")] = "trust/spec",
    status_topic: Annotated[str, typer.Option(help="MQTT swap-status topic.")] = "trust/status",
    verdict_topic: Annotated[
        str, typer.Option(help='MQTT topic of the verdicts (JSON); "" for none.')
    ] = "trust/verdicts",
    explain: Annotated[
        bool,
        typer.Option(
            "--explain",
            help="Also write each verdict (output turned false, trigger fired, and why) "
            "to stderr as a JSON line.",
        ),
    ] = False,
    fabric: Annotated[
        str | None, typer.Option("--fabric", metavar="SYSTEM", help="Run on the RAP fabric.")
    ] = None,
    connect: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to connect, repeatable.")
    ] = None,
    listen: Annotated[
        list[str] | None, typer.Option(help="Zenoh listen endpoint, repeatable.")
    ] = None,
    node: Annotated[
        str, typer.Option(help="The checker's node id on the fabric (hot swap key).")
    ] = "trust_checker",
    fabric_inputs: Annotated[
        str | None,
        typer.Option(
            help='Explicit fabric inputs, JSON: {"stream": {"key": "rap/s/data/x", "field": "f"}}.'
        ),
    ] = None,
    no_default_inputs: Annotated[
        bool,
        typer.Option(
            "--no-default-inputs", help="Do not read the system's trace records and events."
        ),
    ] = False,
    tick: Annotated[
        str, typer.Option(help="Tick policy: message, or window:<duration> (window:10ms).")
    ] = "message",
    mqtt_user: Annotated[
        str, typer.Option("--mqtt-user", metavar="NAME", help="MQTT user name.")
    ] = "",
    mqtt_password_env: Annotated[
        str,
        typer.Option(
            "--mqtt-password-env",
            metavar="VAR",
            help="The environment variable holding the MQTT password.",
        ),
    ] = "",
    mqtt_password_file: Annotated[
        str,
        typer.Option(
            "--mqtt-password-file",
            metavar="FILE",
            help="A file holding the MQTT password (its first line).",
        ),
    ] = "",
    mqtt_tls: Annotated[
        bool, typer.Option("--mqtt-tls", help="MQTT over TLS (implied by --mqtt-ca).")
    ] = False,
    mqtt_ca: Annotated[
        str,
        typer.Option(
            "--mqtt-ca", metavar="PEM", help="The CA the broker's certificate is checked against."
        ),
    ] = "",
    mqtt_cert: Annotated[
        str,
        typer.Option("--mqtt-cert", metavar="PEM", help="A client certificate for the broker."),
    ] = "",
    mqtt_key: Annotated[
        str, typer.Option("--mqtt-key", metavar="PEM", help="The client certificate's key.")
    ] = "",
    redis: Annotated[
        str | None,
        typer.Option(
            "--redis",
            metavar="URL",
            help="Run on Redis pub/sub: redis://HOST:PORT/DB (rediss:// for TLS).",
        ),
    ] = None,
    redis_channels: Annotated[
        str | None,
        typer.Option(
            "--redis-channels",
            metavar="JSON",
            help='Redis channel map, JSON: {"stream": {"channel": "robot/x"}} (default: '
            "the stream's name; an input channel with * ? [ is a pattern).",
        ),
    ] = None,
    redis_spec_channel: Annotated[
        str,
        typer.Option(
            "--redis-spec-channel",
            metavar="CHANNEL",
            help="Redis hot-swap channel (read only with --certs).",
        ),
    ] = "trust/spec",
    redis_status_channel: Annotated[
        str,
        typer.Option(
            "--redis-status-channel", metavar="CHANNEL", help="Redis swap-status channel."
        ),
    ] = "trust/status",
    redis_verdict_channel: Annotated[
        str,
        typer.Option(
            "--redis-verdict-channel",
            metavar="CHANNEL",
            help='Redis channel of the verdicts (JSON); "" for none.',
        ),
    ] = "trust/verdicts",
    redis_verdict_stream: Annotated[
        str,
        typer.Option(
            "--redis-verdict-stream",
            metavar="KEY",
            help="Also XADD each verdict to this Redis stream (field verdict).",
        ),
    ] = "",
    redis_user: Annotated[
        str, typer.Option("--redis-user", metavar="NAME", help="Redis ACL user name.")
    ] = "",
    redis_password_env: Annotated[
        str,
        typer.Option(
            "--redis-password-env",
            metavar="VAR",
            help="The environment variable holding the Redis password.",
        ),
    ] = "",
    redis_password_file: Annotated[
        str,
        typer.Option(
            "--redis-password-file",
            metavar="FILE",
            help="A file holding the Redis password (its first line).",
        ),
    ] = "",
    redis_tls: Annotated[
        bool,
        typer.Option("--redis-tls", help="Redis over TLS (implied by rediss:// and --redis-ca)."),
    ] = False,
    redis_ca: Annotated[
        str,
        typer.Option(
            "--redis-ca", metavar="PEM", help="The CA the server's certificate is checked against."
        ),
    ] = "",
    redis_cert: Annotated[
        str,
        typer.Option("--redis-cert", metavar="PEM", help="A client certificate for Redis."),
    ] = "",
    redis_key: Annotated[
        str, typer.Option("--redis-key", metavar="PEM", help="The client certificate's key.")
    ] = "",
    dds: Annotated[
        int | None,
        typer.Option(
            "--dds",
            metavar="DOMAIN",
            help="Also read inputs from ROS 2 topics over DDS, on this domain (ROS_DOMAIN_ID).",
            show_default=False,
        ),
    ] = None,
    dds_topics: Annotated[
        str | None,
        typer.Option(
            "--dds-topics",
            metavar="JSON",
            help='DDS input map, JSON: {"stream": {"topic": "/robot/x", "type": '
            '"std_msgs/msg/Float64"}} (default: /<stream>, rap_msgs/msg/Frame).',
        ),
    ] = None,
    dds_qos: Annotated[
        int,
        typer.Option(
            "--dds-qos",
            metavar="0|1",
            help="0: best effort (every publisher); 1: reliable, transient-local.",
        ),
    ] = 0,
    certs: Annotated[
        Path | None,
        typer.Option(
            "--certs",
            metavar="DIR",
            envvar=CERTS_ENV,
            help="The certificates rap certs wrote: take hot swaps only from an operator "
            f"(default: ${CERTS_ENV}).",
            show_default=False,
        ),
    ] = None,
    send_swap: Annotated[
        bool,
        typer.Option(
            "--send-swap",
            help="Send SPEC to a running checker (--fabric SYSTEM --node N, --mqtt or "
            "--redis) as a hot swap, signed as --as, and print its answer.",
        ),
    ] = False,
    identity: Annotated[
        str | None,
        typer.Option(
            "--as",
            metavar="NAME",
            envvar=AS_ENV,
            help=f"With --send-swap: sign as this operator (default: ${AS_ENV}).",
            show_default=False,
        ),
    ] = None,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
    metrics: MetricsOpt = None,
    log_file: LogFileOpt = None,
    log_redis: LogRedisOpt = None,
) -> None:
    """Run a trust spec. A mistake exits with code 2 and one 'error:' line.

    Example: python -m trust_checker spec.dsrv --fabric demo --metrics 127.0.0.1:9466"""
    setup_logging(log_level)
    metrics = check_metrics_option(metrics)
    log_redis = check_redis_url(log_redis)
    mqtt_cfg = None
    mqtt_options = (
        mqtt_user or mqtt_password_env or mqtt_password_file or mqtt_tls,
        mqtt_ca or mqtt_cert or mqtt_key,
    )
    if mqtt is None and any(mqtt_options):
        raise fail("the --mqtt-* options go with --mqtt HOST:PORT - give it, or drop them")
    if mqtt is not None:
        host, port = _mqtt_address(mqtt)
        try:
            mqtt_cfg = MqttConfig(
                host=host,
                port=port,
                topics=_decode(topics, TopicMap, "--topics") if topics else {},
                tagged=tagged,
                spec_topic=spec_topic,
                status_topic=status_topic,
                verdict_topic=verdict_topic,
                username=mqtt_user,
                password_env=mqtt_password_env,
                password_file=mqtt_password_file,
                tls=mqtt_tls,
                ca=mqtt_ca,
                cert=mqtt_cert,
                key=mqtt_key,
            )
        except ValueError as exc:
            text = str(exc)
            for field, option in _MQTT_OPTIONS:
                text = text.replace(f"({field})", f"({option})")
            raise fail(text) from None
        try:
            mqtt_credentials(mqtt_cfg)  # a missing password or certificate: said now
        except ConfigError as exc:
            raise fail(str(exc)) from None
    redis_options = (
        redis_channels is not None,
        redis_spec_channel != "trust/spec",
        redis_status_channel != "trust/status",
        redis_verdict_channel != "trust/verdicts",
        redis_verdict_stream or redis_user or redis_password_env or redis_password_file,
        redis_tls or redis_ca or redis_cert or redis_key,
    )
    if redis is None and any(redis_options):
        raise fail("the --redis-* options go with --redis URL - give it, or drop them")
    redis_cfg = None
    if redis is not None:
        try:
            redis_cfg = RedisConfig(
                url=redis,
                channels=(
                    _decode(redis_channels, ChannelMap, "--redis-channels")
                    if redis_channels
                    else {}
                ),
                tagged=tagged,
                spec_channel=redis_spec_channel,
                status_channel=redis_status_channel,
                verdict_channel=redis_verdict_channel,
                verdict_stream=redis_verdict_stream,
                username=redis_user,
                password_env=redis_password_env,
                password_file=redis_password_file,
                tls=redis_tls,
                ca=redis_ca,
                cert=redis_cert,
                key=redis_key,
            )
        except ValueError as exc:
            text = str(exc)
            for field, option in _REDIS_OPTIONS:
                text = text.replace(f"({field})", f"({option})")
            raise fail(text) from None
        try:
            redis_credentials(redis_cfg)  # a missing password or certificate: said now
        except ConfigError as exc:
            raise fail(str(exc)) from None
    dds_cfg = None
    if dds is None and (dds_topics is not None or dds_qos):
        raise fail("the --dds-* options go with --dds DOMAIN - give it, or drop them")
    if dds is not None:
        try:
            dds_cfg = DdsConfig(
                domain=dds,
                topics=_decode(dds_topics, DdsTopic, "--dds-topics") if dds_topics else {},
                qos=dds_qos,
            )
        except ValueError as exc:
            raise fail(f"--dds: {exc}") from None
    fabric_cfg = None
    zconf = None
    if fabric is not None:
        fabric_cfg, zconf = _fabric_config(
            fabric, node, fabric_inputs, not no_default_inputs, connect, listen
        )
    try:
        config = ServiceConfig(
            node=node, tick=tick, mqtt=mqtt_cfg, redis=redis_cfg, fabric=fabric_cfg, dds=dds_cfg
        )
    except ValueError as exc:  # the tick policy
        raise fail(f"--tick: {exc}") from None
    live = [cfg for cfg in (mqtt_cfg, redis_cfg, fabric_cfg, dds_cfg) if cfg is not None]
    if input_file is not None and live:
        raise fail(
            "--input-file runs alone - drop --mqtt, --redis, --fabric and --dds, or --input-file"
        )
    parsed = _load(spec)
    if send_swap:
        if input_file is not None or check:
            raise fail("--send-swap sends SPEC to a running checker - drop --input-file/--check")
        if dds_cfg is not None:
            raise fail("--send-swap: DDS takes no hot swap - use --fabric, --mqtt or --redis")
        if len(live) != 1:
            raise fail(
                "--send-swap: give one of --fabric SYSTEM (with --node), --mqtt HOST:PORT "
                "or --redis URL"
            )
        if fabric_cfg is not None and not connect:
            raise fail(
                "--send-swap --fabric: give --connect ENDPOINT (the checker's listen "
                "endpoint, or a router of the system)"
            )
        signer = _signer(certs, identity)
        code = anyio.run(_send_swap, spec, mqtt_cfg, redis_cfg, fabric_cfg, zconf, node, signer)
        raise typer.Exit(code)
    if check:
        typer.echo(
            f"{spec}: ok (inputs: {', '.join(parsed.inputs) or 'none'}; "
            f"outputs: {', '.join(parsed.outputs) or 'none'})"
        )
        return
    if input_file is not None:
        _run_file(parsed, input_file, explain=explain)
        return
    if not live:
        raise fail(f"nothing to run on - {_HOW_TO_RUN}")
    if log_redis is not None and not fabric:
        raise fail("--log-redis names the stream by system - give --fabric SYSTEM too")
    verifier = _verifier(certs)
    logs = LogContext(system=fabric or "", process=node)
    open_file_log(log_file, logs)
    # uvloop when present, as RAP's other services run: a cheaper wake-up per message
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    try:
        anyio.run(
            partial(_serve, logs=logs, metrics=metrics, log_redis=log_redis, verifier=verifier),
            config,
            parsed,
            zconf,
            explain,
            backend_options={"use_uvloop": use_uvloop},
        )
    except FabricError as exc:  # e.g. a listen endpoint that is taken
        raise fail(f"{exc} - check --listen and --connect", 1) from None


def _decode(text: str, value_type: type[T], option: str) -> dict[str, T]:
    try:
        return decode_map(text, value_type, option)
    except ConfigError as exc:
        example = _EXAMPLES.get(value_type, "{}")
        raise fail(f"{exc} - write a JSON object like {example}") from None


def _load(spec: Path) -> Spec:
    try:
        return load_spec(spec)
    except TextFileError as exc:
        raise fail(str(exc)) from None
    except SpecError as exc:
        for problem in exc.problems:
            typer.echo(str(problem), err=True)
        n = len(exc.problems)
        raise fail(
            f"{spec}: {n} problem{'s' if n != 1 else ''}; not started - fix them (above) "
            "and run again"
        ) from None


def _fabric_config(
    system: str,
    node: str,
    inputs_json: str | None,
    default_inputs: bool,
    connect: list[str] | None,
    listen: list[str] | None,
) -> tuple[FabricConfig, ZenohConfig]:
    check_system(system, "--fabric")
    try:
        keys.admin(system, node, "swap")
    except keys.KeyError_ as exc:
        raise fail(f"--node {node!r}: {exc}") from None
    listen_eps = check_endpoints("--listen", listen)
    connect_eps = check_endpoints("--connect", connect)
    inputs = _decode(inputs_json, FabricInput, "--fabric-inputs") if inputs_json else {}
    if not inputs and not default_inputs:
        raise fail("--no-default-inputs leaves nothing to read - give --fabric-inputs too")
    cfg = FabricConfig(system=system, inputs=inputs, default_inputs=default_inputs)
    zconf = ZenohConfig(listen=listen_eps or ZenohConfig().listen, connect=connect_eps)
    return cfg, zconf


def _run_file(spec: Spec, path: Path, *, explain: bool = False) -> None:
    """Every tick's console lines (and with ``explain`` its verdicts on stderr) as soon
    as it is computed; a failing tick ends the run with its error line, after every
    earlier tick was written."""
    try:
        trace = load_trace(read_source(path, "trace"), str(path))
    except (TextFileError, InputError) as exc:
        raise fail(str(exc)) from None
    runner = SpecRunner(spec)
    explainer = Explainer(runner) if explain else None
    n = len(trace.ticks)
    try:
        for inputs in trace.ticks:
            if explainer is not None:
                outs, verdicts = explainer.step(inputs)
                _write(console_lines(outs), verdict_lines([to_message(v) for v in verdicts]))
            else:
                _write(console_lines(runner.step(inputs)), "")
        if explainer is not None:
            for outs, verdicts in explainer.drain():
                _write(console_lines(outs), verdict_lines([to_message(v) for v in verdicts]))
        else:
            for outs in runner.drain():
                _write(console_lines(outs), "")
    except InputError as exc:  # the tick was not taken: runner.tick is its number
        where = trace.where(str(path), runner.tick)
        raise fail(f"{where}: {exc}") from None
    except EvalError as exc:  # the tick was taken
        failed = runner.tick - 1
        after = " (after the last input)" if failed >= n else ""
        raise fail(
            f"{trace.where(str(path), failed)}: {exc}{after} - the spec cannot compute this "
            "tick: guard the expression in the spec, or fix the trace's values",
            1,
        ) from None
    finally:
        sys.stdout.flush()


def _write(out: str, err: str) -> None:
    """A tick's console lines (buffered) and its verdict lines (stderr, after the tick's
    console lines)."""
    if out:
        sys.stdout.write(out)
    if err:
        sys.stdout.flush()
        sys.stderr.write(err)
        sys.stderr.flush()


async def _serve(
    config: ServiceConfig,
    spec: Spec,
    zconf: ZenohConfig | None,
    explain: bool,
    *,
    logs: LogContext,
    metrics: str | None = None,
    log_redis: str | None = None,
    verifier: Verifier | None = None,
) -> None:
    sink = ConsoleSink(explain=explain)
    counts = VerdictCounts()
    sinks: list[Sink] = [sink, counts]
    running: list[TrustService] = []
    # served from a daemon thread of its own until the process ends
    collector = TrustCollector(
        counts, lambda: running[0] if running else None, system=logs.system, node=config.node
    )
    start_metrics(metrics, [collector], what="trust checker")
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        if zconf is None:
            async with open_service(config, spec, sinks=sinks, verifier=verifier) as service:
                running.append(service)
                await _wait_for_signal(signals)
            return
        async with (
            ZenohFabric(zconf) as fabric,
            publish_logs(fabric, logs, node=config.node, redis_url=log_redis),
            open_service(config, spec, fabric=fabric, sinks=sinks, verifier=verifier) as service,
        ):
            running.append(service)
            await _wait_for_signal(signals)


def _verifier(certs: Path | None) -> Verifier | None:
    """The CA the checker checks hot swaps against (None: it takes every swap)."""
    if certs is None:
        return None
    try:
        return load_verifier(certs)
    except IdentityError as exc:
        raise fail(f"--certs: {exc}") from None


def _signer(certs: Path | None, identity: str | None) -> Signer | None:
    """Who --send-swap signs as (None: it sends the swap unsigned)."""
    if identity is None:
        return None
    if certs is None:
        raise fail(
            f"--as {identity}: where are the certificates? give --certs DIR or set {CERTS_ENV}"
        )
    try:
        return load_signer(certs, identity)
    except IdentityError as exc:
        raise fail(f"--as {identity}: {exc}") from None


async def _send_swap(
    spec: Path,
    mqtt_cfg: MqttConfig | None,
    redis_cfg: RedisConfig | None,
    fabric_cfg: FabricConfig | None,
    zconf: ZenohConfig | None,
    node: str,
    signer: Signer | None,
) -> int:
    """Send the spec in ``spec`` to a running checker; print its answer. 0: swapped;
    1: refused or not answered."""
    from .io.auth import fabric_swap, signed_update, update_body

    text = await anyio.to_thread.run_sync(read_source, spec)
    path = spec.name
    if fabric_cfg is not None and zconf is not None:
        key = keys.admin(fabric_cfg.system, node, "swap")
        conf = ZenohConfig(listen=[], connect=zconf.connect)
        try:
            async with ZenohFabric(conf) as fab:
                await fab.wait_matched(key, queryable=True, timeout=5.0)
                status = await fabric_swap(fab, key, text, signer=signer, path=path)
        except RapError as exc:
            typer.echo(f"error: {exc}", err=True)
            return 1
    elif redis_cfg is not None:
        from .io.redis import redis_swap

        try:
            status = await redis_swap(redis_cfg, text, node=node, signer=signer, path=path)
        except RapError as exc:
            typer.echo(f"error: {exc}", err=True)
            return 1
    else:
        assert mqtt_cfg is not None
        import aiomqtt
        import msgspec

        from .io.mqtt import mqtt_credentials as creds_of

        creds = await anyio.to_thread.run_sync(creds_of, mqtt_cfg)
        topic = mqtt_cfg.spec_topic
        if signer is not None:
            payload = signed_update(signer, topic, text, path)
        else:
            payload = update_body(text, path)
        decode = msgspec.json.Decoder(TrustSpecStatus).decode
        try:
            async with aiomqtt.Client(
                mqtt_cfg.host,
                mqtt_cfg.port,
                timeout=mqtt_cfg.timeout,
                username=mqtt_cfg.username or None,
                password=creds.password,
                tls_context=creds.tls,
            ) as client:
                await client.subscribe(mqtt_cfg.status_topic)
                await client.publish(topic, payload, qos=1)
                with anyio.fail_after(10):
                    async for message in client.messages:
                        try:
                            status = decode(bytes(message.payload))
                        except msgspec.DecodeError:
                            continue
                        if status.node == node:
                            break
        except (aiomqtt.MqttError, TimeoutError) as exc:
            what = "no status came within 10 s" if isinstance(exc, TimeoutError) else exc
            typer.echo(
                f"error: --mqtt {mqtt_cfg.host}:{mqtt_cfg.port}: {what} - is the checker "
                f"--node {node} running there, on --spec-topic {topic}?",
                err=True,
            )
            return 1
    if status.ok:
        typer.echo(
            f"{node}: swapped to {path} at tick {status.tick}: inputs "
            f"{', '.join(status.inputs) or 'none'}; outputs {', '.join(status.outputs) or 'none'}"
        )
        return 0
    for problem in status.problems:
        typer.echo(problem, err=True)
    typer.echo(f"error: {node}: the swap was refused; the running spec stays", err=True)
    return 1


async def _wait_for_signal(signals: AsyncIterator[int]) -> None:
    async for signum in signals:
        log.info("received %s; stopping", signal.Signals(signum).name)
        return


if __name__ == "__main__":
    run_cli(cli, prog="python -m trust_checker")
