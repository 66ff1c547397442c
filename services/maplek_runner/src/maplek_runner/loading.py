"""A compute node's share of a deployment plan: import each component's Node, check it
against the plan, apply its config.

    doc = load_plan("plan.yaml")                 # rap_schemas.PlanError: file:line:col
    share = load_share(doc, "laptop")            # LoadError: file:line:col of the component
    share.nodes                                  # [Node, ...] for rap_sdk.run_nodes

Only the components mapped to the chosen compute node are imported: a module that needs
hardware or packages of another machine is never imported here.
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass
from typing import Any

from rap_schemas import ComponentSpec, DeploymentPlan, PlanDocument
from rap_schemas.yamlconf import Location, parse_location
from rap_sdk import ConfigError, Node

from .errors import LoadError

__all__ = ["LoadedComponent", "NodeShare", "import_node", "load_share"]

log = logging.getLogger(__name__)

_MISSING = object()


@dataclass(frozen=True, slots=True)
class LoadedComponent:
    name: str
    spec: ComponentSpec
    node: Node
    where: str
    """``file:line:col`` of the component in the plan."""


@dataclass(frozen=True, slots=True)
class NodeShare:
    """What a deployment plan runs on one compute node."""

    document: PlanDocument
    compute_node: str
    components: tuple[LoadedComponent, ...]

    @property
    def plan(self) -> DeploymentPlan:
        return self.document.plan

    @property
    def system(self) -> str:
        return self.document.plan.system

    @property
    def nodes(self) -> list[Node]:
        return [c.node for c in self.components]


def _fail(doc: PlanDocument, loc: Location, problem: str, *, key: bool = False) -> LoadError:
    return LoadError(f"{doc.where(loc, key=key)}: {problem}")


def import_node(module: str) -> Node:
    """The Node named by a ``package.module:attribute`` spec. Raises :class:`LoadError`
    (without a plan position) saying what failed and how to fix it."""
    module_name, _, attr = module.partition(":")
    try:
        mod = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if module_name == missing or module_name.startswith(missing + "."):
            fix = (
                "check the spelling of module:, and that its package is installed in the "
                "environment that runs the runner"
            )
        else:
            fix = f"the module imports {missing!r}, which is not installed: install it"
        raise LoadError(f"cannot import module {module_name!r}: {exc}; {fix}") from exc
    except Exception as exc:  # importing runs the module's code: any error can surface
        raise LoadError(
            f"cannot import module {module_name!r}: {type(exc).__name__}: {exc}; fix the "
            "error in that module (run 'python -c \"import "
            f"{module_name}\"' to see the traceback)"
        ) from exc
    obj: Any = getattr(mod, attr, _MISSING)
    if obj is _MISSING:
        found = sorted(name for name, value in vars(mod).items() if isinstance(value, Node))
        listing = f"its Nodes are: {', '.join(found)}" if found else "it declares no Node"
        raise LoadError(
            f"module {module_name!r} has no attribute {attr!r}; {listing}; name one of them "
            "after the colon"
        )
    if not isinstance(obj, Node):
        raise LoadError(
            f"{module} is a {type(obj).__name__}, not a rap_sdk.Node; point module: at a "
            f'Node object, e.g. \'{attr} = Node("{attr}", stage="monitor")\' in {module_name}'
        )
    obj.implementation = module
    return obj


def load_share(doc: PlanDocument, compute_node: str) -> NodeShare:
    """Import, check and configure the components that ``doc`` maps to ``compute_node``.

    Raises :class:`LoadError` naming the plan's ``file:line:col`` of the component at
    fault. Applying a component's ``config`` changes its Node object (``Node.configure``).
    A compute node with no components (one that only hosts knowledge, say) has an empty
    share.
    """
    plan = doc.plan
    if compute_node not in plan.compute_nodes:
        raise LoadError(
            f"{doc.source}: compute node {compute_node!r} is not in the plan; its compute "
            f"nodes are: {', '.join(plan.compute_nodes)}"
        )
    loaded: list[LoadedComponent] = []
    for name, spec in plan.components_on(compute_node).items():
        loc = ("components", name)
        if spec.external or spec.run:
            continue  # described for the checks; something else runs it (rap up: run:)
        if spec.module is None and spec.stage is None and spec.role == "knowledge":
            continue  # a design's knowledge store: RAP's knowledge service plays it
        if spec.module is None:
            raise _fail(
                doc,
                loc,
                f"component {name!r} has no module: it is to be generated; run "
                "'rap generate' on the model, or name its Node with 'module: "
                "package.module:attribute' (or mark it 'external: true' if something "
                "other than RAP runs it)",
                key=True,
            )
        try:
            node = import_node(spec.module)
        except LoadError as exc:
            raise _fail(doc, (*loc, "module"), f"component {name!r}: {exc}") from exc.__cause__
        twin = next((c for c in loaded if c.node is node), None)
        if twin is not None:
            raise _fail(
                doc,
                (*loc, "module"),
                f"component {name!r} loads the same Node object as component {twin.name!r} "
                f"({twin.where}); a Node runs once: declare a second Node",
            )
        if node.name != name:
            raise _fail(
                doc,
                loc,
                f"component {name!r} loads Node {node.name!r}; a component is known on the "
                f"fabric by its Node's name: rename the component to {node.name!r}",
                key=True,
            )
        if node.stage != spec.stage:
            declared = node.stage.value if node.stage is not None else "no stage"
            planned = spec.stage.value if spec.stage is not None else "no stage"
            raise _fail(
                doc,
                (*loc, "stage") if spec.stage is not None else loc,
                f"component {name!r} is {planned!r} in the plan, but Node "
                f"{node.name!r} declares {declared!r}; make them agree",
                key=spec.stage is None,
            )
        loaded.append(LoadedComponent(name, spec, node, doc.where(loc, key=True)))
    for component in loaded:
        _configure(doc, component)
    return NodeShare(doc, compute_node, tuple(loaded))


def _configure(doc: PlanDocument, component: LoadedComponent) -> None:
    if not component.spec.config:
        return
    loc: tuple[Any, ...] = ("components", component.name, "config")
    if component.node.config is None:
        raise _fail(
            doc,
            loc,
            f"component {component.name!r}: Node {component.node.name!r} declares no "
            "config Struct, so it takes no config; remove config: from the plan",
        )
    try:
        component.node.configure(dict(component.spec.config))
    except ConfigError as exc:
        message = str(exc)
        at = message.rfind("`$")
        if at >= 0:
            loc = (*loc, *parse_location(message[at + 1 : message.find("`", at + 1)]))
        raise _fail(
            doc, loc, f"component {component.name!r}: {message}; fix config: in the plan"
        ) from None
    log.debug("configured %s: %s", component.name, component.node.config)
