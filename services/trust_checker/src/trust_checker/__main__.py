"""``python -m trust_checker SPEC``: run a trust spec on a trace file, MQTT or the fabric.

    python -m trust_checker spec.dsrv --input-file trace.txt      console lines, then exit
    python -m trust_checker spec.dsrv --check                     validate only
    python -m trust_checker spec.dsrv --mqtt 127.0.0.1:1883 [--topics JSON] [--tagged]
    python -m trust_checker spec.dsrv --fabric SYSTEM [--connect EP ...] [--listen EP ...]

A spec with errors prints every problem (file:line:col, the text, a hint) and exits with
code 2 without starting. Live modes print each output as a console line
(``name[tick] = Int(7)``) and run until SIGTERM or SIGINT, then exit 0.

Live modes publish verdicts (a Bool output turned false, a trigger fired; see
docs/trust_checker.md, "Explanations and triggers") on the fabric and on MQTT
(``--verdict-topic``). ``--explain`` also writes each verdict to stderr as one JSON line
(``rap.TrustVerdict``); stdout stays the reference checker's console lines.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import signal
import sys
from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Annotated

import anyio
import msgspec
import typer
from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustVerdict, keys
from rap_schemas.plan import ENDPOINT
from rap_sdk import FabricError, ZenohConfig, ZenohFabric

from .config import ConfigError, FabricConfig, FabricInput, MqttConfig, TopicMap, decode_map
from .errors import InputError, SpecError, TrustError
from .explain import Explainer, to_message
from .io.fabric import FabricTransport
from .io.mqtt import MqttTransport
from .io.ports import OutputLike
from .io.session import Session
from .io.specs import load_text
from .io.ticks import TickPolicy, parse_tick_policy
from .lang import load_spec
from .lang.ast import Spec
from .monitor import Monitor
from .tracefile import read_trace, run_trace
from .values import console

cli = typer.Typer(add_completion=False, help=__doc__)

log = logging.getLogger("trust_checker")


def _fail(message: str, code: int) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code)


def _write_stdout(text: str) -> None:
    sys.stdout.write(text)
    sys.stdout.flush()


def _write_stderr(text: str) -> None:
    sys.stderr.write(text)
    sys.stderr.flush()


_encode_json = msgspec.json.Encoder().encode


def verdict_lines(verdicts: Sequence[TrustVerdict]) -> str:
    """``--explain``: one JSON line per verdict (the ``rap.TrustVerdict`` wire form)."""
    return "".join(_encode_json(v).decode() + "\n" for v in verdicts)


class ConsoleSink:
    """Console lines on stdout for every output (the reference checker's format), and
    with ``explain`` each verdict as a JSON line on stderr.

    A tick's lines are queued and :meth:`run` writes whatever has queued in one call on a
    worker thread, so neither a slow reader nor a write per tick holds up the session
    (and the sinks after this one); only ``MAX_PENDING`` unwritten chunks make a tick
    wait. What is queued when the checker stops is still written."""

    MAX_PENDING = 10_000

    def __init__(self, *, explain: bool = False) -> None:
        self.explain = explain
        self._send, self._receive = anyio.create_memory_object_stream[tuple[bool, str]](
            self.MAX_PENDING
        )

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        text = "".join(f"{o.stream}[{o.tick}] = {console(o.value)}\n" for o in outs)
        if text:
            await self._put((False, text))

    async def verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        if self.explain and verdicts:
            await self._put((True, verdict_lines(verdicts)))

    async def _put(self, chunk: tuple[bool, str]) -> None:
        """Queue without yielding to the event loop while there is room (a tick's lines
        cost no task switch); wait only when ``MAX_PENDING`` chunks are unwritten."""
        try:
            self._send.send_nowait(chunk)
        except anyio.WouldBlock:
            await self._send.send(chunk)

    async def status(self, status: TrustSpecStatus) -> None:
        """Swap outcomes are logged by the session."""

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        task_status.started()
        try:
            async for first in self._receive:
                await anyio.to_thread.run_sync(_write_chunks, self._drain(first))
        finally:
            with anyio.CancelScope(shield=True):
                rest = self._drain(None)
                if rest:
                    await anyio.to_thread.run_sync(_write_chunks, rest)

    def _drain(self, first: tuple[bool, str] | None) -> list[tuple[bool, str]]:
        chunks = [] if first is None else [first]
        while True:
            try:
                chunks.append(self._receive.receive_nowait())
            except (anyio.WouldBlock, anyio.EndOfStream, anyio.ClosedResourceError):
                return chunks


def _write_chunks(chunks: list[tuple[bool, str]]) -> None:
    out = "".join(text for err, text in chunks if not err)
    err = "".join(text for is_err, text in chunks if is_err)
    if out:
        _write_stdout(out)
    if err:
        _write_stderr(err)


def _mqtt_address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, 1883
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--mqtt {text!r} is not HOST:PORT, e.g. 127.0.0.1:1883")
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
        bool, typer.Option("--tagged", help='Publish D5.2 tagged values ({"Int": 42}).')
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
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "INFO",
) -> None:
    """Run a trust spec. A spec with errors exits with code 2."""
    level = logging.getLevelNamesMapping().get(log_level.upper())
    if level is None:
        raise _fail(f"--log-level {log_level!r}: use DEBUG, INFO, WARNING or ERROR", 2)
    logging.basicConfig(
        level=level, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        policy = parse_tick_policy(tick)
        mqtt_cfg = None
        if mqtt is not None:
            host, port = _mqtt_address(mqtt)
            topic_map = decode_map(topics, TopicMap, "--topics") if topics else {}
            mqtt_cfg = MqttConfig(
                host=host,
                port=port,
                topics=topic_map,
                tagged=tagged,
                spec_topic=spec_topic,
                status_topic=status_topic,
                verdict_topic=verdict_topic,
            )
        fabric_cfg = None
        zconf: ZenohConfig | None = None
        if fabric is not None:
            fabric_cfg, zconf = _fabric_config(
                fabric, node, fabric_inputs, not no_default_inputs, connect, listen
            )
    except (ValueError, keys.KeyError_) as exc:
        raise _fail(str(exc), 2) from None

    try:
        parsed = load_spec(Path(spec))
    except SpecError as exc:
        for problem in exc.problems:
            typer.echo(str(problem), err=True)
        n = len(exc.problems)
        raise _fail(f"{spec}: {n} problem{'s' if n != 1 else ''}; not started", 2) from None
    except OSError as exc:
        raise _fail(f"cannot read spec {spec}: {exc.strerror or exc}", 2) from None
    if check:
        typer.echo(
            f"{spec}: ok (inputs: {', '.join(parsed.inputs) or 'none'}; "
            f"outputs: {', '.join(parsed.outputs) or 'none'})"
        )
        return
    if input_file is not None:
        if mqtt_cfg is not None or fabric_cfg is not None:
            raise _fail("--input-file runs alone; drop --mqtt/--fabric", 2)
        _run_file(parsed, input_file, explain=explain)
        return
    if mqtt_cfg is None and fabric_cfg is None:
        raise _fail("nothing to run on: give --input-file, --mqtt HOST:PORT or --fabric SYSTEM", 2)
    # uvloop when present, as RAP's other services run: a cheaper wake-up per message
    use_uvloop = importlib.util.find_spec("uvloop") is not None
    try:
        anyio.run(
            _serve,
            parsed,
            policy,
            mqtt_cfg,
            fabric_cfg,
            zconf,
            node,
            explain,
            backend_options={"use_uvloop": use_uvloop},
        )
    except FabricError as exc:  # e.g. a listen endpoint that is taken
        raise _fail(str(exc), 1) from None


def _fabric_config(
    system: str,
    node: str,
    inputs_json: str | None,
    default_inputs: bool,
    connect: list[str] | None,
    listen: list[str] | None,
) -> tuple[FabricConfig, ZenohConfig]:
    keys.system_pattern(system)
    keys.admin(system, node, "swap")
    for option, endpoints in (("--listen", listen), ("--connect", connect)):
        for endpoint in endpoints or ():
            if not ENDPOINT.fullmatch(endpoint):
                raise ConfigError(
                    f"{option} {endpoint!r} is not a Zenoh endpoint; write "
                    "'<protocol>/<address>', e.g. 'tcp/127.0.0.1:7447'"
                )
    inputs = decode_map(inputs_json, FabricInput, "--fabric-inputs") if inputs_json else {}
    if not inputs and not default_inputs:
        raise ConfigError("--no-default-inputs needs --fabric-inputs: nothing would be read")
    cfg = FabricConfig(system=system, node=node, inputs=inputs, default_inputs=default_inputs)
    zconf = ZenohConfig(
        listen=list(listen) if listen else ZenohConfig().listen, connect=list(connect or [])
    )
    return cfg, zconf


def _explain_trace(spec: Spec, ticks: list[dict[str, object]]) -> list[tuple[str, str]]:
    """``run_trace`` with explanations: per tick, its console lines and its verdicts'
    JSON lines."""
    ex = Explainer(Monitor(spec))
    out: list[tuple[str, str]] = []
    steps = [ex.step(t) for t in ticks]
    steps.append(ex.finish())
    for outs, verdicts in steps:
        text = "".join(f"{o.stream}[{o.tick}] = {console(o.value)}\n" for o in outs)
        out.append((text, verdict_lines([to_message(v) for v in verdicts])))
    return out


def _run_file(spec: Spec, trace: Path, *, explain: bool = False) -> None:
    try:
        text = trace.read_text(encoding="utf-8")
    except OSError as exc:
        raise _fail(f"cannot read trace {trace}: {exc.strerror or exc}", 2) from None
    try:
        ticks = read_trace(text, str(trace))
        if explain:
            for console_text, verdict_text in _explain_trace(spec, ticks):
                _write_stdout(console_text)
                _write_stderr(verdict_text)
            return
        lines = run_trace(spec, ticks)
    except SpecError as exc:
        for problem in exc.problems:
            typer.echo(str(problem), err=True)
        raise _fail(f"{trace}: not run", 2) from None
    except InputError as exc:
        raise _fail(str(exc), 2) from None
    except TrustError as exc:
        raise _fail(str(exc), 1) from None
    for line in lines:
        print(line)


async def _serve(
    spec: Spec,
    policy: TickPolicy,
    mqtt_cfg: MqttConfig | None,
    fabric_cfg: FabricConfig | None,
    zconf: ZenohConfig | None,
    node: str,
    explain: bool = False,
) -> None:
    console_sink = ConsoleSink(explain=explain)
    session = Session(
        Monitor(spec),
        loader=load_text,
        sinks=[console_sink],
        policy=policy,
        node=node,
        explain=True,
    )
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with contextlib.AsyncExitStack() as stack:
            zfabric = None
            if fabric_cfg is not None and zconf is not None:
                zfabric = await stack.enter_async_context(ZenohFabric(zconf))
            tg = await stack.enter_async_context(anyio.create_task_group())
            tg.start_soon(_stop_on_signal, signals, tg.cancel_scope)
            await tg.start(console_sink.run)
            await tg.start(session.run)
            if mqtt_cfg is not None:
                await tg.start(MqttTransport(session, mqtt_cfg).run)
            if fabric_cfg is not None and zfabric is not None:
                await tg.start(FabricTransport(session, zfabric, fabric_cfg).run)
            log.info(
                "ready: inputs %s, outputs %s, tick policy %s",
                ", ".join(session.monitor.inputs) or "none",
                ", ".join(session.monitor.outputs) or "none",
                policy,
            )
    s = session.stats
    log.info(
        "stopped after %d ticks: %d outputs, %d verdicts, %d rejected, %d input errors, "
        "%d eval errors",
        s.ticks,
        s.outputs,
        s.verdicts,
        s.rejected,
        s.input_errors,
        s.eval_errors,
    )


async def _stop_on_signal(signals: AsyncIterator[int], scope: anyio.CancelScope) -> None:
    async for signum in signals:
        log.info("received %s; stopping", signal.Signals(signum).name)
        scope.cancel()
        return


if __name__ == "__main__":
    cli()
