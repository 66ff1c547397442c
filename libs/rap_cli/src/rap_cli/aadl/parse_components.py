"""Building the syntax model of files, packages and component classifiers (features,
subcomponents, connections, modes) from lark's parse tree."""

from __future__ import annotations

from lark import Token, Tree

from rap_cli.aadl import syntax as s
from rap_cli.aadl.parse_properties import _PropertyBuilder
from rap_cli.aadl.parse_tree import _has, _text, _toks, _tree, _trees, _words

_FEATURE_WORDS = {"EVENT", "DATA", "PORT", "PARAMETER", "BUS", "SUBPROGRAM", "GROUP"}
_FEATURE_WORDS |= {"VIRTUAL", "ACCESS", "FEATURE"}
_DIRECTIONS: dict[str, s.Direction] = {"in": "in", "out": "out", "in out": "in out"}
_TYPE_ORDER = ("prototypes", "features", "flows", "modes", "properties", "annex_subclause")
_IMPL_ORDER = (
    *("prototypes", "subcomponents", "calls", "connections"),
    *("flows", "modes", "properties", "annex_subclause"),
)


class _Builder(_PropertyBuilder):
    """Turns the parse tree into :mod:`syntax` nodes, collecting notes (what is skipped)
    and diagnostics (what the grammar cannot check)."""

    # -- files, packages, classifiers

    def file(self, tree: Tree[Token]) -> s.AadlFile:
        """The whole file; notes sorted by place."""
        packages = tuple(self.package(t) for t in _trees(tree, "package"))
        sets = tuple(self.property_set(t) for t in _trees(tree, "property_set"))
        notes = tuple(sorted(self.notes, key=lambda n: (n.loc.line, n.loc.column)))
        return s.AadlFile(self.source, packages, sets, notes)

    def package(self, tree: Tree[Token]) -> s.Package:
        """A package; the withs of both sections are merged, in order."""
        start, end = _trees(tree, "pkg_name")
        name = _text(start)
        self.check_end(_toks(start, "IDENT", "DCOLON"), _toks(end, "IDENT", "DCOLON"), "package")
        withs: list[str] = []
        with_locs: list[s.Loc] = []
        renames: list[s.Renames] = []
        sections: dict[str, list[s.Declaration]] = {"public_section": [], "private_section": []}
        for section in _trees(tree, "public_section", "private_section"):
            for item in _trees(section, "with_clause", "renames"):
                if item.data == "with_clause":
                    withs += [_text(n) for n in _trees(item, "pkg_name")]
                    with_locs += [self.loc(n) for n in _trees(item, "pkg_name")]
                elif item.data == "renames":
                    renames.append(self.renames(item))
            for child in _trees(section, "component_type", "component_impl", "annex_library"):
                if child.data == "component_type":
                    sections[section.data].append(self.component_type(child))
                elif child.data == "component_impl":
                    sections[section.data].append(self.component_impl(child))
                else:
                    annex = _toks(child, "IDENT")[0]
                    message = (
                        f"annex library {annex} of package {name} skipped: "
                        "RAP does not read annexes"
                    )
                    self.note(child, message)
        properties = self.properties(_tree(tree, "properties"))
        return s.Package(
            self.loc(tree),
            name,
            tuple(withs),
            tuple(renames),
            tuple(sections["public_section"]),
            tuple(sections["private_section"]),
            properties,
            tuple(with_locs),
        )

    def renames(self, tree: Tree[Token]) -> s.Renames:
        """One of the four renames forms."""
        idents = _toks(tree, "IDENT")
        if _has(tree, "ALL"):
            parts = [c for c in tree.children if isinstance(c, Token)][1:-2]
            return s.Renames(self.loc(tree), None, "all", "".join(parts))
        package = _tree(tree, "pkg_name")
        if package is not None:
            return s.Renames(self.loc(tree), str(idents[0]), "package", _text(package))
        category = _tree(tree, "category")
        kind = _words(category) if category is not None else "feature group"
        target = _tree(tree, "classifier_ref")
        return s.Renames(self.loc(tree), str(idents[0]), kind, _text(target) if target else "")

    def component_type(self, tree: Tree[Token]) -> s.ComponentType:
        """A component type and its sections."""
        category = _words(_trees(tree, "category")[0])
        idents = _toks(tree, "IDENT")
        name = str(idents[0])
        owner = f"{category} type '{name}'"
        self.check_end([idents[0]], [idents[-1]], f"the {category} type")
        extends = _tree(tree, "classifier_ref")
        self.check_order(tree, _TYPE_ORDER, owner)
        features = [
            self.feature(f) for sec in _trees(tree, "features") for f in _trees(sec, "feature")
        ]
        modes, transitions, requires = self.modes(tree)
        return s.ComponentType(
            self.loc(tree),
            category,
            name,
            _text(extends) if extends is not None else None,
            tuple(features),
            modes,
            transitions,
            requires,
            self.section_properties(tree),
            self.skipped(tree, owner),
        )

    def component_impl(self, tree: Tree[Token]) -> s.ComponentImpl:
        """A component implementation and its sections."""
        category = _words(_trees(tree, "category")[0])
        idents = _toks(tree, "IDENT")
        type_name, impl_name = str(idents[0]), str(idents[1])
        name = f"{type_name}.{impl_name}"
        owner = f"{category} implementation '{name}'"
        self.check_end(idents[:2], idents[-2:], f"the {category} implementation")
        extends = _tree(tree, "classifier_ref")
        self.check_order(tree, _IMPL_ORDER, owner)
        subcomponents = [
            self.subcomponent(c)
            for sec in _trees(tree, "subcomponents")
            for c in sec.children
            if isinstance(c, Tree)
        ]
        connections = [
            self.connection(c)
            for sec in _trees(tree, "connections")
            for c in sec.children
            if isinstance(c, Tree)
        ]
        modes, transitions, requires = self.modes(tree)
        if requires:
            message = (
                f"'requires modes' in {owner} - AADL v2 allows it in component types only; "
                "declare the modes with 'modes'"
            )
            self.report(tree, "warning", message)
        return s.ComponentImpl(
            self.loc(tree),
            category,
            name,
            type_name,
            impl_name,
            _text(extends) if extends is not None else None,
            tuple(subcomponents),
            tuple(connections),
            modes,
            transitions,
            self.section_properties(tree),
            self.skipped(tree, owner),
        )

    def check_order(self, tree: Tree[Token], order: tuple[str, ...], owner: str) -> None:
        """Warn about sections out of the standard's order, or repeated."""
        last = -1
        seen: set[str] = set()
        for section in tree.children:
            if not isinstance(section, Tree) or section.data not in order:
                continue
            rank = order.index(section.data)
            word = "annex" if section.data == "annex_subclause" else section.data
            if section.data in seen and section.data != "annex_subclause":
                message = f"a second '{word}' section in {owner} - merge it into the first"
                self.report(section, "warning", message)
            elif rank < last:
                sequence = ", ".join(o.replace("_subclause", "") for o in order)
                message = (
                    f"the '{word}' section of {owner} is out of order "
                    f"- AADL v2 orders sections as {sequence}"
                )
                self.report(section, "warning", message)
            seen.add(section.data)
            last = max(last, rank)

    def skipped(self, tree: Tree[Token], owner: str) -> int:
        """Note the sections RAP does not model (``none`` ones need no note); return the
        number of flow declarations."""
        flows = 0
        counted = {"flows": "flow", "calls": "call_sequence", "prototypes": "prototype"}
        what = {"flows": "flow declaration", "calls": "call sequence", "prototypes": "prototype"}
        for section in tree.children:
            if not isinstance(section, Tree):
                continue
            if section.data in counted:
                count = len(_trees(section, counted[section.data]))
                flows += count if section.data == "flows" else 0
                if count:
                    kind = what[section.data]
                    message = (
                        f"{count} {kind}(s) of {owner} skipped: RAP does not model {section.data}"
                    )
                    self.note(section, message)
            elif section.data == "annex_subclause" and not _has(section, "NONE"):
                annex = _toks(section, "IDENT")[0]
                self.note(section, f"annex {annex} of {owner} skipped: RAP does not read annexes")
        return flows

    # -- features, subcomponents, connections, modes

    def feature(self, tree: Tree[Token]) -> s.Feature:
        """A feature; its kind is its keywords less direction and access."""
        name = _toks(tree, "IDENT")[0]
        direction = _tree(tree, "direction")
        access = _toks(tree, "PROVIDES", "REQUIRES")
        classifier = _tree(tree, "classifier_ref")
        return s.Feature(
            self.loc(name),
            str(name),
            " ".join(str(t).lower() for t in _toks(tree, *_FEATURE_WORDS)),
            _DIRECTIONS[_words(direction)] if direction is not None else None,
            ("provides" if access[0].type == "PROVIDES" else "requires") if access else None,
            _text(classifier) if classifier is not None else None,
            self.dims(tree),
            self.block(tree),
            _has(tree, "REFINED"),
            _has(tree, "INVERSE"),
        )

    def dims(self, tree: Tree[Token]) -> tuple[str, ...]:
        """Array sizes as written, ``''`` for ``[]``."""
        dims = _tree(tree, "array_dims")
        return tuple(_text(d) for d in _trees(dims, "array_dim")) if dims is not None else ()

    def subcomponent(self, tree: Tree[Token]) -> s.Subcomponent:
        """A subcomponent."""
        name = _toks(tree, "IDENT")[0]
        classifier = _tree(tree, "classifier_ref")
        return s.Subcomponent(
            self.loc(name),
            str(name),
            _words(_trees(tree, "category")[0]),
            _text(classifier) if classifier is not None else None,
            self.dims(tree),
            self.in_modes(tree),
            self.block(tree),
            _has(tree, "REFINED"),
        )

    def connection(self, tree: Tree[Token]) -> s.Connection:
        """A connection, named or not."""
        name = _toks(tree, "IDENT")
        source, dest = _trees(tree, "element_path")
        return s.Connection(
            self.loc(tree),
            str(name[0]) if name else None,
            _words(_trees(tree, "connection_kind")[0]),
            _text(source),
            _text(dest),
            _has(tree, "BIARROW"),
            self.in_modes(tree),
            self.block(tree),
        )

    def modes(
        self, tree: Tree[Token]
    ) -> tuple[tuple[s.Mode, ...], tuple[s.ModeTransition, ...], bool]:
        """Modes, transitions, and whether they are ``requires modes``."""
        modes: list[s.Mode] = []
        transitions: list[s.ModeTransition] = []
        requires = False
        for section in _trees(tree, "modes"):
            requires = requires or _has(section, "REQUIRES")
            for item in _trees(section, "mode"):
                name = _toks(item, "IDENT")[0]
                modes.append(
                    s.Mode(self.loc(name), str(name), _has(item, "INITIAL"), self.block(item))
                )
            transitions += [self.transition(t) for t in _trees(section, "mode_transition")]
        return tuple(modes), tuple(transitions), requires

    def transition(self, tree: Tree[Token]) -> s.ModeTransition:
        """A mode transition, named or not."""
        sources = _trees(tree, "transition_sources")[0]
        idents = _toks(tree, "IDENT")  # [name,] destination
        return s.ModeTransition(
            self.loc(tree),
            str(idents[0]) if len(idents) == 2 else None,
            tuple(str(t) for t in _toks(sources, "IDENT")),
            tuple(_text(p) for p in _trees(tree, "element_path")),
            str(idents[-1]),
            self.block(tree),
        )
