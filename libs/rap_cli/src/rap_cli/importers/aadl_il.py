"""Import RPIO's AADL-IL (``design.json``) into RAP's system model.

AADL-IL is the JSON RPIO writes from an AADL design: a root system with nested
``_systemList``; each system has ``_processList`` (processes, with ``_featureList`` ports
and ``_threadList``), ``_processorList`` (compute nodes, with ``_IP``, ``_propertyList``
and ``_bindingList``: copies of the processes they run) and ``_messageList``. Every port
embeds a copy of its message (``_message``). The design has no connection list: RPIO
connects ports by name, so each port's ``topic`` is its name as written and the model's
checks connect an output and an input of the same kind family on the same topic.

Mapping (each part's place in the file goes to :attr:`Imported.where`):

- the root system's ``_name`` -> ``system`` (characters a name may not hold become ``_``);
- a process -> a component (``module`` none: to generate); its stage from its name
  (Monitor, Analyse/Analysis, Plan, Legitimate/Legitimation, Execute; Knowledge -> role
  ``knowledge``); ``_formalism`` and ``_containerization`` -> properties;
- a feature ``inport``/``outport``/``inoutport`` -> a port ``in``/``out``/``in-out``;
  ``_type`` ``event``/``data``/``event data`` (or ``data event``) -> kind
  ``event``/``data``/``event-data``; ``_message._name`` -> its type; a port name that is
  no valid name (``/spin_config``) is cleaned (``spin_config``), the topic keeps it;
- a thread -> a thread of its component: ``_eventTrigger`` set -> sporadic dispatch (the
  trigger kept as a property), none -> no dispatch;
- a processor -> a compute node (``_IP`` -> address; ``rap_backbone``, ``_propertyList``
  and its own features -> properties); each entry of ``_bindingList`` binds the process of
  that name to it;
- ``_messageList`` -> messages; ``_dataType`` ``Float_64`` -> ``float64``, ``Boolean`` ->
  ``bool``, ... (:data:`.aadl_il_names.DATA_TYPES`); ``Array``, which gives no element type, ->
  ``list[float64]`` with a note;
- a system's own features are its boundary, which the model has no place for (a note):
  for a system made of processes, its processes' ports are what connects; a system with no
  processes (the managed system) runs outside RAP and is no component either. (As an
  external component it would only add findings that its inputs have no producer and it
  has no compute node.)

Diagnostics the design alone can give: JSON that does not parse (``readable`` False, at
the error's line), a member of the wrong JSON type, an unknown feature or port type, a
binding naming no process or a second binding, and a port whose message the message
lists omit - that message is still created from the port's copy and the port gets an
error. The model's own checks (an input nobody produces, a type mismatch, a process on no
processor) are left to ``plan_findings``/``model_findings``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rap_schemas.plan import (
    ComponentSpec,
    ComputeNode,
    DeploymentPlan,
    Dispatch,
    FieldSpec,
    MessageSpec,
    PortSpec,
    ThreadSpec,
)

from ..diagnostics import Diagnostic, Loc, Severity
from . import Imported
from .aadl_il_json import JsonDocument, JsonPath, read_json
from .aadl_il_names import DATA_TYPES, clean_name, description, stage_or_role
from .aadl_il_nodes import processor, scalar_text

__all__ = ["import_aadl_il"]

_ARRAY = "list[float64]"
_DIRECTIONS = {"inport": "in", "outport": "out", "inoutport": "in-out", "inout": "in-out"}
_KINDS = {"event": "event", "data": "data", "event data": "event-data", "data event": "event-data"}
_MAX_SYSTEM_DEPTH = 32


def import_aadl_il(path: Path) -> Imported:
    """Import one AADL-IL file (see the module docstring). Never raises: a file that
    cannot be read or is not JSON gives ``readable`` False and its error."""
    document, diagnostics = read_json(path)
    if document is None:
        return Imported(None, diagnostics, sources=[str(path)], readable=False)
    if not isinstance(document.value, dict):
        diagnostics.append(
            Diagnostic(
                str(path),
                1,
                1,
                "error",
                "the design is not a JSON object - an AADL-IL "
                "design.json is one object with _name, _systemList, _messageList",
            )
        )
        return Imported(None, diagnostics, sources=[str(path)], readable=False)
    return _Importer(document).run()


class _Importer:
    """One AADL-IL document -> an :class:`Imported` (see the module docstring)."""

    def __init__(self, document: JsonDocument) -> None:
        self.doc = document
        self.out = Imported(None, sources=[document.source])
        self.messages: dict[str, MessageSpec] = {}
        self.declared: dict[str, JsonPath] = {}
        self.components: dict[str, ComponentSpec] = {}
        self.nodes: dict[str, ComputeNode] = {}
        self.bound: dict[str, JsonPath] = {}

    # ---- reporting and locations

    def _loc(self, path: JsonPath) -> Loc:
        """Where the member at ``path`` is: an object at its ``_name`` (the line a reader
        looks for), anything else where it starts."""
        named = (*path, "_name")
        return self.doc.loc(named if named in self.doc.positions else path)

    def _report(self, path: JsonPath, severity: Severity, message: str) -> None:
        """Report once (messages and systems are walked twice: once for messages)."""
        loc = self._loc(path)
        found = Diagnostic(loc.file, loc.line, loc.column, severity, message)
        if found not in self.out.diagnostics:
            self.out.diagnostics.append(found)

    def _where(self, model: tuple[object, ...], path: JsonPath) -> None:
        self.out.where[model] = self._loc(path)

    # ---- typed access to the untrusted JSON

    def _items(
        self, obj: dict[str, Any], key: str, at: JsonPath
    ) -> list[tuple[JsonPath, dict[str, Any]]]:
        """The objects of the list ``obj[key]`` with their paths (missing: none)."""
        value = obj.get(key)
        if value is None:
            return []
        if not isinstance(value, list):
            self._report((*at, key), "error", f"{key} is not a list - write [ ... ] here")
            return []
        out = []
        for i, item in enumerate(value):
            if isinstance(item, dict):
                out.append(((*at, key, i), item))
            else:
                self._report(
                    (*at, key, i),
                    "error",
                    f'item {i} of {key} is not an object - each item is {{ "_name": ..., ... }}',
                )
        return out

    def _name(self, obj: dict[str, Any], at: JsonPath, what: str) -> str | None:
        name = obj.get("_name")
        if isinstance(name, str) and name:
            return name
        self._report(at, "error", f"this {what} has no _name - give it one; it is left out")
        return None

    # ---- the walk

    def run(self) -> Imported:
        root = self.doc.value
        system = self._name(root, (), "system") or Path(self.doc.source).stem
        self._where(("system",), ("_name",))
        self._where((), ())
        self._collect_messages(root, (), 0)
        self._system(root, (), 0)
        self.out.plan = DeploymentPlan(
            system=clean_name(system),
            compute_nodes=self.nodes,
            components=self.components,
            messages=self.messages,
            doc=description(root),
        )
        return self.out

    def _subsystems(
        self, obj: dict[str, Any], at: JsonPath, depth: int
    ) -> list[tuple[JsonPath, dict[str, Any]]]:
        if depth >= _MAX_SYSTEM_DEPTH:
            self._report(
                at,
                "error",
                f"systems nest deeper than {_MAX_SYSTEM_DEPTH} levels - "
                "flatten the design; the deeper ones are left out",
            )
            return []
        return self._items(obj, "_systemList", at)

    def _collect_messages(self, system: dict[str, Any], at: JsonPath, depth: int) -> None:
        """Every ``_messageList`` first, so that ports anywhere find their messages."""
        for path, msg in self._items(system, "_messageList", at):
            name = self._name(msg, path, "message")
            if name is None:
                continue
            mname = clean_name(name)
            if mname in self.declared:
                first = self.doc.loc(self.declared[mname])
                self._report(
                    path,
                    "warning",
                    f"message {name!r} is declared again (first at "
                    f"line {first.line}) - keep one; the first is used",
                )
                continue
            self.declared[mname] = path
            self.messages[mname] = MessageSpec(
                fields=self._fields(msg, path, ("messages", mname)),
                origin=f"aadl-il message {name}",
                doc=description(msg),
            )
            self._where(("messages", mname), (*path, "_name"))
        for path, sub in self._subsystems(system, at, depth):
            self._collect_messages(sub, path, depth + 1)

    def _fields(
        self, msg: dict[str, Any], at: JsonPath, model: tuple[object, ...] | None
    ) -> dict[str, FieldSpec]:
        fields: dict[str, FieldSpec] = {}
        for path, feat in self._items(msg, "_featureList", at):
            fname = self._name(feat, path, "field")
            if fname is None:
                continue
            raw = feat.get("_dataType")
            if not isinstance(raw, str) or not raw:
                if model is not None:
                    self._report(
                        path,
                        "error",
                        f"field {fname!r} has no _dataType - give "
                        "one, e.g. Float_64; it is typed bytes here",
                    )
                ftype, doc = "bytes", "AADL-IL gives no _dataType"
            elif raw == "Array":
                ftype, doc = _ARRAY, "AADL-IL 'Array' gives no element type; float64 assumed"
                if model is not None:
                    self._report(
                        path,
                        "note",
                        f"field {fname!r} is an Array without an "
                        "element type - it becomes list[float64]; fix the type if "
                        "the items are not float64",
                    )
            else:
                ftype = DATA_TYPES.get(raw) or clean_name(raw)
                doc = ""
            fields[fname] = FieldSpec(type=ftype, doc=doc, ge=0 if raw == "Natural" else None)
            if model is not None:
                self._where((*model, "fields", fname), (*path, "_name"))
                self._where((*model, "fields", fname, "type"), (*path, "_dataType"))
        return fields

    def _system(self, system: dict[str, Any], at: JsonPath, depth: int) -> None:
        name = system.get("_name") if isinstance(system.get("_name"), str) else "?"
        processes = self._items(system, "_processList", at)
        subsystems = self._subsystems(system, at, depth)
        for path, proc in processes:
            self._process(proc, path, str(name))
        features = self._items(system, "_featureList", at)
        if features:
            names = ", ".join(
                f"{f.get('_name')} ({f.get('_featureType')}, {f.get('_type')})" for _, f in features
            )
            what = (
                "its processes' ports are imported"
                if processes or subsystems
                else "it has no processes: it runs outside RAP (a managed system), so it is "
                "no component"
            )
            self._report(
                at,
                "note",
                f"system {name!r} has features {names}: the boundary of a system, which the "
                f"model has no place for; {what}",
            )
        for path, proc in self._items(system, "_processorList", at):
            processor(self, proc, path, str(name))
        for path, sub in subsystems:
            self._system(sub, path, depth + 1)

    def _add_component(self, name: str, spec: ComponentSpec, at: JsonPath, what: str) -> str | None:
        cname = clean_name(name)
        if cname in self.components:
            first = self.out.where[("components", cname)]
            self._report(
                at,
                "error",
                f"{what} {name!r} is declared again (first at line "
                f"{first.line}) - rename one; this one is left out",
            )
            return None
        self.components[cname] = spec
        self._where(("components", cname), (*at, "_name"))
        return cname

    def _process(self, proc: dict[str, Any], at: JsonPath, system: str) -> None:
        name = self._name(proc, at, "process")
        if name is None:
            return
        cname = clean_name(name)
        stage, role = stage_or_role(name)
        ports = self._ports(self._items(proc, "_featureList", at), cname)
        threads: dict[str, ThreadSpec] = {}
        for path, thread in self._items(proc, "_threadList", at):
            tname = self._name(thread, path, "thread")
            if tname is None:
                continue
            threads[clean_name(tname)] = self._thread(thread, path, name, ports)
            self._where(("components", cname, "threads", clean_name(tname)), (*path, "_name"))
        properties = {
            key[1:]: scalar_text(proc[key])
            for key in ("_formalism", "_containerization")
            if key in proc
        }
        self._add_component(
            name,
            ComponentSpec(
                stage=stage,
                role=role,
                ports=ports,
                threads=threads,
                origin=f"aadl-il process {system}.{name}",
                properties=properties,
                doc=description(proc),
            ),
            at,
            "process",
        )

    def _thread(
        self, thread: dict[str, Any], at: JsonPath, process: str, ports: dict[str, PortSpec]
    ) -> ThreadSpec:
        trigger = thread.get("_eventTrigger")
        for path, feat in self._items(thread, "_featureList", at):
            fname = feat.get("_name")
            if isinstance(fname, str) and clean_name(fname) not in ports:
                self._report(
                    path,
                    "note",
                    f"thread feature {fname!r} is not a port of process "
                    f"{process!r}; the model keeps ports per component - add it to the "
                    "process's features if it is one",
                )
        return ThreadSpec(
            dispatch=Dispatch(kind="sporadic") if trigger else None,
            properties={"event_trigger": str(trigger)} if trigger else {},
            origin=f"aadl-il thread {process}.{thread.get('_name')}",
            doc=description(thread),
        )

    def _ports(
        self, features: list[tuple[JsonPath, dict[str, Any]]], comp: str
    ) -> dict[str, PortSpec]:
        ports: dict[str, PortSpec] = {}
        for path, feat in features:
            name = self._name(feat, path, "feature")
            if name is None:
                continue
            pname = clean_name(name)
            model = ("components", comp, "ports", pname)
            raw_dir = feat.get("_featureType")
            direction = _DIRECTIONS.get(str(raw_dir).lower().replace(" ", ""))
            if direction is None:
                self._report(
                    path,
                    "error",
                    f"feature {name!r} has _featureType {raw_dir!r} - "
                    "use inport, outport or inoutport; it is left out",
                )
                continue
            raw_kind = feat.get("_type")
            kind = _KINDS.get(" ".join(str(raw_kind).lower().split()))
            if kind is None:
                self._report(
                    (*path, "_type"),
                    "error",
                    f"port {name!r} has _type {raw_kind!r} - "
                    "use event, data or event data; it is taken as event data",
                )
                kind = "event-data"
            if pname in ports:
                self._report(
                    path,
                    "error",
                    f"port {name!r} is declared twice - rename one; the second is left out",
                )
                continue
            properties = {
                key[1:]: scalar_text(feat[key])
                for key in ("_initialValue", "_valueReference")
                if key in feat
            }
            if pname != name:
                self._report(
                    path,
                    "note",
                    f"port {name!r} is named {pname!r} in the model (a "
                    f"name holds only letters, digits and '_.-~+:@=%,'); its topic "
                    f"stays {name!r}",
                )
            ports[pname] = PortSpec(
                direction=direction,  # type: ignore[arg-type]
                kind=kind,  # type: ignore[arg-type]
                type=self._port_type(feat, path, name),
                topic=name,
                origin=f"aadl-il feature {comp}.{name}",
                properties=properties,
                doc=description(feat),
            )
            self._where(model, (*path, "_name"))
            self._where((*model, "type"), (*path, "_message"))
        return ports

    def _port_type(self, feat: dict[str, Any], at: JsonPath, port: str) -> str | None:
        """The port's message; one the message lists omit is created from the port's copy
        (an error at the port says so); a copy that differs from the declaration warns."""
        msg = feat.get("_message")
        if msg is None:
            return None
        mpath = (*at, "_message")
        if not isinstance(msg, dict) or not isinstance(msg.get("_name"), str):
            self._report(
                mpath,
                "error",
                f"port {port!r}: _message is not a message object with "
                "a _name - give one or null for a bare event; the port carries none",
            )
            return None
        name = msg["_name"]
        mname = clean_name(name)
        copy = self._fields(msg, mpath, None)
        if mname in self.declared:
            if copy != self.messages[mname].fields:
                first = self.doc.loc(self.declared[mname])
                self._report(
                    mpath,
                    "warning",
                    f"port {port!r} embeds a copy of message {name!r} "
                    f"that differs from its declaration at line {first.line} - "
                    "regenerate the design; the declaration is used",
                )
            return mname
        self._report(
            at,
            "error",
            f"port {port!r} uses message {name!r}, which the design does "
            f"not declare - add {name} to a _messageList (it is created here from the "
            "port's copy)",
        )
        if mname not in self.messages:
            known = (
                "its fields are taken from the port's copy" if copy else "its fields are unknown"
            )
            self.messages[mname] = MessageSpec(
                fields=copy,
                origin=f"aadl-il message {name} (from port {port})",
                doc=f"Not in the design's message lists; used by port {port} - {known}.",
            )
            self._where(("messages", mname), (*mpath, "_name"))
            for fname in copy:
                self._where(("messages", mname, "fields", fname), (*mpath, "_featureList"))
        return mname
