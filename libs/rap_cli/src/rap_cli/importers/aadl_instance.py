"""The instance tree of an AADL design: the root system implementation and, under it,
every subcomponent that RAP's model has a place for, with implementations followed
(``extends`` merged by :class:`~.aadl_index.Index`).

Instantiated categories: system, abstract, process, thread, thread group, processor,
virtual processor, bus, virtual bus, device, memory (data subcomponents are message
fields, subprograms are code: neither is an instance). An array subcomponent
``s: process P[3]`` yields the instances ``s_1``, ``s_2``, ``s_3`` (1-based, as AADL
counts; ``s_1_2`` for two dimensions); a path naming ``s`` alone names all of them.

Property values of an instance (:meth:`Instance.properties`) come from its classifier's
type and implementation chains, the subcomponent's ``{ }`` block, then the ``applies
to`` associations of the implementations above it, the outermost one winning as in AADL.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..diagnostics import Diagnostic, Loc
from .aadl_index import Classifier, Index, Resolved, diagnostic

__all__ = ["INSTANTIATED", "Instance", "build_tree", "value_text"]

INSTANTIATED = frozenset(
    {
        "system",
        "abstract",
        "process",
        "thread",
        "thread group",
        "processor",
        "virtual processor",
        "bus",
        "virtual bus",
        "device",
        "memory",
    }
)
MAX_DEPTH = 32
"""Deeper instance trees are refused (a design nests a handful of levels)."""
MAX_ARRAY = 1000
"""Larger arrays are refused (an array of processes this big is a typo)."""


@dataclass(eq=False)
class Instance:
    """One component instance. ``path`` is the names from the root (``()`` for the
    root); ``classifier`` is None when it did not resolve or none was given."""

    name: str
    path: tuple[str, ...]
    category: str
    loc: Loc
    resolved: Resolved
    classifier: Classifier | None
    parent: Instance | None = None
    sub: s.Subcomponent | None = None
    children: dict[str, Instance] = field(default_factory=dict)
    arrays: dict[str, list[Instance]] = field(default_factory=dict)
    subnames: dict[str, str] = field(default_factory=dict)
    """Every subcomponent name of the implementation (data ones too), by norm name."""
    features: dict[str, s.Feature] = field(default_factory=dict)
    own: list[s.PropertyAssociation] = field(default_factory=list)
    contained: list[tuple[int, s.PropertyAssociation]] = field(default_factory=list)
    feature_props: dict[str, list[tuple[int, s.PropertyAssociation]]] = field(default_factory=dict)

    @property
    def dotted(self) -> str:
        return ".".join(self.path)

    @property
    def depth(self) -> int:
        return len(self.path)

    @property
    def opaque(self) -> bool:
        """Its features are unknown (its classifier did not resolve to the import's)."""
        return self.classifier is None

    @property
    def impl(self) -> Classifier | None:
        c = self.classifier
        return c if c is not None and isinstance(c.decl, s.ComponentImpl) else None

    @property
    def classifier_text(self) -> str:
        """The classifier as the origin names it: qualified, or as written."""
        if self.classifier is not None:
            return self.classifier.qualified
        if self.sub is not None and self.sub.classifier is not None:
            return self.sub.classifier
        return "(no classifier)"

    def properties(self) -> list[s.PropertyAssociation]:
        """Every association that applies to it, the winning one last."""
        contained = [a for _, a in sorted(self.contained, key=lambda x: -x[0])]
        return self.own + contained

    def port_properties(self, feature: str) -> list[s.PropertyAssociation]:
        """The associations of feature ``feature``: its declaration's, then contained."""
        declared = self.features.get(norm(feature))
        own = list(declared.properties) if declared is not None else []
        contained = self.feature_props.get(norm(feature), [])
        return own + [a for _, a in sorted(contained, key=lambda x: -x[0])]

    def walk(self) -> list[Instance]:
        """It and every instance under it, depth first, in declaration order."""
        out = [self]
        for child in self.children.values():
            out += child.walk()
        return out

    def resolve(self, path: str) -> list[Instance]:
        """The instances a dotted path of subcomponents names from here (several for
        an array); empty when a name does not exist."""
        here = [self]
        for part in path.split("."):
            key = norm(part.partition("[")[0])
            step: list[Instance] = []
            for inst in here:
                if key in inst.arrays:
                    step += inst.arrays[key]
                elif key in inst.children:
                    step.append(inst.children[key])
            if not step:
                return []
            here = step
        return here


def build_tree(index: Index, root: Classifier, diagnostics: list[Diagnostic]) -> Instance:
    """Instantiate ``root`` and everything under it; then attach the ``applies to``
    associations of every implementation to what they name."""
    top = Instance(root.type_name, (), "system", root.decl.loc, root, root)
    _fill(index, top, diagnostics, {root.key})
    for inst in top.walk():
        _attach(index, inst, diagnostics)
    return top


def _fill(
    index: Index, inst: Instance, diagnostics: list[Diagnostic], ancestors: set[tuple[str, str]]
) -> None:
    c = inst.classifier
    if c is None:
        return
    inst.features = index.features(c)
    inst.own = index.properties(c) + (list(inst.sub.properties) if inst.sub else [])
    if inst.impl is None:
        return
    for sub, package in index.subcomponents(c):
        inst.subnames[norm(sub.name)] = sub.name
        if sub.category not in INSTANTIATED:
            continue
        resolved = (
            index.resolve(sub.classifier, package, sub.loc) if sub.classifier is not None else None
        )
        classifier = resolved if isinstance(resolved, Classifier) else None
        if classifier is not None and classifier.key in ancestors:
            message = (
                f"{sub.name}: {classifier.qualified} contains itself (through "
                f"{inst.dotted or inst.name}) - an implementation cannot be its own subcomponent"
            )
            diagnostics.append(diagnostic(sub.loc, "error", message))
            classifier = None
        if inst.depth >= MAX_DEPTH:
            message = f"{sub.name}: the design nests more than {MAX_DEPTH} levels - flatten it"
            diagnostics.append(diagnostic(sub.loc, "error", message))
            return
        names = _array_names(sub, diagnostics)
        made: list[Instance] = []
        for name in names:
            child = Instance(
                name, (*inst.path, name), sub.category, sub.loc, resolved, classifier, inst, sub
            )
            inst.children[norm(name)] = child
            made.append(child)
            seen = ancestors | ({classifier.key} if classifier is not None else set())
            _fill(index, child, diagnostics, seen)
        if sub.dims:
            inst.arrays[norm(sub.name)] = made


def _array_names(sub: s.Subcomponent, diagnostics: list[Diagnostic]) -> list[str]:
    """``name`` or, for an array, ``name_1`` .. ``name_N``."""
    if not sub.dims:
        return [sub.name]
    sizes: list[int] = []
    for dim in sub.dims:
        if dim.isdigit() and 0 < int(dim) <= MAX_ARRAY:
            sizes.append(int(dim))
            continue
        message = (
            f"{sub.name}: the array size [{dim}] is not a number from 1 to {MAX_ARRAY} - "
            "write the size as an integer; one instance is made"
        )
        diagnostics.append(diagnostic(sub.loc, "warning", message))
        sizes.append(1)
    return [
        "_".join([sub.name, *map(str, combo)])
        for combo in itertools.product(*(range(1, n + 1) for n in sizes))
    ]


_IGNORED_TARGETS = frozenset({"actual_connection_binding"})


def _attach(index: Index, inst: Instance, diagnostics: list[Diagnostic]) -> None:
    """Give each ``applies to`` association of ``inst``'s implementation to the
    instances, features or connections it names; report a path that names nothing."""
    c = inst.impl
    if c is None:
        return
    connections = {norm(conn.name) for conn in index.connections(c) if conn.name}
    modes = {norm(m.name) for m in index.modes(c)[0]}
    for assoc, _package in index.contained(c):
        for path in assoc.applies_to:
            head, _, last = path.rpartition(".")
            if not head and norm(last) in connections | modes:
                continue  # a connection's or a mode's property: read where it is used
            targets = inst.resolve(path)
            if targets:
                for target in targets:
                    target.contained.append((inst.depth, assoc))
                continue
            owners = inst.resolve(head) if head else [inst]
            feats = [o for o in owners if norm(last) in o.features or o.opaque]
            if owners and feats:
                for owner in feats:
                    owner.feature_props.setdefault(norm(last), []).append((inst.depth, assoc))
                continue
            if owners and any(not o.opaque and o.impl is None for o in owners):
                continue  # inside a leaf we do not instantiate (a data field, a mode)
            if norm(assoc.simple_name) in _IGNORED_TARGETS:
                continue
            where = f"{c.qualified}" if not head else f"{head} in {c.qualified}"
            message = (
                f"{assoc.name} applies to {path}, but {where} has no subcomponent, "
                f"feature or connection {last!r} - fix the path (it is relative to "
                f"{c.qualified})"
            )
            binding = "binding" in norm(assoc.simple_name)
            diagnostics.append(diagnostic(assoc.loc, "error" if binding else "warning", message))


def value_text(value: s.PropertyValue) -> str:
    """A property value as AADL writes it (for ``properties:`` of the model)."""
    if isinstance(value, s.IntValue | s.RealValue):
        return f"{value.value} {value.unit}" if value.unit else str(value.value)
    if isinstance(value, s.StringValue):
        return value.value
    if isinstance(value, s.BoolValue):
        return "true" if value.value else "false"
    if isinstance(value, s.EnumValue):
        return value.literal
    if isinstance(value, s.NameValue):
        return value.name
    if isinstance(value, s.RangeValue):
        text = f"{value_text(value.low)} .. {value_text(value.high)}"
        return text + (f" delta {value_text(value.delta)}" if value.delta is not None else "")
    if isinstance(value, s.ListValue):
        return "(" + ", ".join(value_text(v) for v in value.items) + ")"
    if isinstance(value, s.RecordValue):
        return "[" + " ".join(f"{f.name} => {value_text(f.value)};" for f in value.fields) + "]"
    if isinstance(value, s.ReferenceValue):
        return f"reference ({value.path})"
    if isinstance(value, s.ClassifierValue):
        return f"classifier ({value.name})"
    return f"compute ({value.function})"
