"""The architecture rules of ``hil`` and ``services``, checked from the source with ``ast``.

Nothing here imports the code it checks: a broken or slow import cannot hide a violation, and
function-level imports count like module-level ones (they run sooner or later). Every check
returns :class:`Violation` records naming file, line and rule, so a failing test says what to
fix. ``python -m tests.layering`` prints them all.

The layer table: a module may import modules of its own layer or below. A module's layer is
the entry whose prefix matches it (the prefix itself or anything under it), the longest prefix
winning; ``hil`` alone is the package ``__init__``, not everything under it. A module that
matches no entry is reported, so a new package gets a deliberate place in the table.
"""

from __future__ import annotations

import ast
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# layer -> module prefixes (see the module docstring for how a module finds its layer)
LAYERS: dict[int, tuple[str, ...]] = {
    0: ("hil.messages", "hil.nav.types", "hil.sensor_table"),
    1: ("hil.nav",),
    2: ("hil.sensors", "hil.estimators", "hil.timesync", "hil.faults"),
    3: ("hil.fusion", "hil.can", "hil.wire", "hil.wellknown"),
    4: ("hil.nodes",),
    # hil.can's transports and file adapters are I/O: python-can buses over Zenoh and over
    # local sockets, the transmitter that sends a node's frames, MCAP as a python-can log
    5: (
        "hil.can.bus",
        "hil.can.node",
        "hil.can.zenoh_bus",
        "hil.can.local_bus",
        "hil.can.frame_bus",
        "hil.can.mcap_io",
        "hil.bus",
        "hil.campaign",
        "hil.record",
        "hil.report",
        "hil.runtime",
        "hil.runners",
        "hil.progress",
        "hil.monitor",
        "hil.foxglove_server",
        "hil.foxglove_relay",
        "hil.schemas_io",
        "hil",
    ),
    6: ("hil.bench",),
    7: ("services",),
    8: ("hil.cli",),
}
EXACT_ONLY = frozenset({"hil"})  # prefixes that name one module, not a subtree

ROOT_PACKAGES = ("hil", "services")
COMPOSITION_ROOT = "hil.cli"  # the one module under hil/ that may import services

# Pure packages: no I/O, no clock, no threads; the same inputs give the same outputs.
PURE_PACKAGES = (
    "hil.nav",
    "hil.estimators",
    "hil.fusion",
    "hil.timesync",
    "hil.sensors",
    "hil.nodes",
    "hil.wire",
    "hil.wellknown",  # Foxglove's well-known types from the messages (foxglove-sdk encodes, no I/O)
)
IMPURE_IMPORTS = ("zenoh", "time", "threading", "subprocess")
# python-can is a transport too; hil.nodes may use its ``can.Message`` data type.
NO_PYTHON_CAN = ("hil.nav", "hil.estimators", "hil.fusion", "hil.timesync", "hil.sensors", "hil.wire")

MAX_FUNCTION_LINES = 120


@dataclass(frozen=True)
class Violation:
    """One broken rule, at the import or ``def`` that breaks it."""

    rule: str
    path: str
    line: int
    message: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: [{self.rule}] {self.message}"


@dataclass(frozen=True)
class Import:
    """One imported name as written, and the internal module it resolves to (if any)."""

    line: int
    name: str  # absolute dotted name as imported (relative imports resolved)
    target: str | None  # the most specific scanned module it loads, None if third-party


@dataclass
class Module:
    name: str
    path: Path
    rel: str  # path relative to the scanned root, for messages
    tree: ast.Module
    imports: list[Import] = field(default_factory=list)


def module_name(rel: Path) -> str:
    """``hil/nav/__init__.py`` -> ``hil.nav``; ``hil/nav/types.py`` -> ``hil.nav.types``."""
    parts = list(rel.with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _raw_imports(tree: ast.Module, name: str, is_package: bool) -> Iterable[tuple[int, str, list[str]]]:
    """(line, absolute base, imported names) of every import statement, at any depth."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, []
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                # the package the relative import starts from
                pkg = name.split(".") if is_package else name.split(".")[:-1]
                keep = len(pkg) - (node.level - 1)
                anchor = ".".join(pkg[: max(keep, 0)])
                base = f"{anchor}.{base}" if base and anchor else (anchor or base)
            yield node.lineno, base, [a.name for a in node.names]


def _resolve(name: str, known: set[str]) -> str | None:
    """The longest scanned module that ``name`` is or lies under, None for third-party names."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        cand = ".".join(parts[:i])
        if cand in known:
            return cand
    return None


def load_modules(root: Path, packages: Sequence[str] = ROOT_PACKAGES) -> dict[str, Module]:
    """Parse every ``.py`` under ``root/<package>`` and resolve its imports."""
    mods: dict[str, Module] = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root)
            name = module_name(rel)
            mods[name] = Module(name, path, rel.as_posix(), ast.parse(path.read_text(), filename=str(path)))
    known = set(mods)
    for mod in mods.values():
        is_package = mod.path.name == "__init__.py"
        for line, base, names in _raw_imports(mod.tree, mod.name, is_package):
            if not names:
                mod.imports.append(Import(line, base, _resolve(base, known)))
                continue
            for n in names:
                full = f"{base}.{n}" if base else n
                # ``from pkg import sub`` loads pkg.sub when it is a module, else a name of pkg
                target = full if full in known else _resolve(base, known)
                imp = Import(line, full if full in known else base, target)
                if imp not in mod.imports:  # ``from m import a, b`` is one import of m
                    mod.imports.append(imp)
    return mods


def _edges(mods: dict[str, Module]) -> dict[str, dict[str, int]]:
    """module -> {imported internal module: first line}; self-imports dropped."""
    graph: dict[str, dict[str, int]] = {m: {} for m in mods}
    for mod in mods.values():
        for imp in mod.imports:
            if imp.target is not None and imp.target != mod.name:
                prev = graph[mod.name].get(imp.target)
                graph[mod.name][imp.target] = imp.line if prev is None else min(prev, imp.line)
    return graph


def _sccs(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Strongly connected components (Tarjan, iterative: the graph can be deep)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work: list[tuple[str, Iterable[str]]] = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    out.append(sorted(comp))
    return out


def _shortest_cycle(graph: dict[str, dict[str, int]], start: str, members: set[str]) -> list[str]:
    """Shortest ``start -> ... -> start`` inside one component (BFS, sorted for stable output)."""
    prev: dict[str, str] = {}
    queue = deque([start])
    seen = {start}
    while queue:
        v = queue.popleft()
        for w in sorted(graph[v]):
            if w not in members:
                continue
            if w == start:
                chain = [v]
                while chain[-1] != start:
                    chain.append(prev[chain[-1]])
                return [*reversed(chain), start]
            if w not in seen:
                seen.add(w)
                prev[w] = v
                queue.append(w)
    return [start]  # unreachable for a real component


def check_cycles(mods: dict[str, Module]) -> list[Violation]:
    """No import cycle; each one reported as a chain with the line of every edge."""
    graph = _edges(mods)
    out: list[Violation] = []
    reported: set[tuple[str, ...]] = set()
    for comp in _sccs(graph):
        if len(comp) < 2:
            continue
        members = set(comp)
        covered: set[str] = set()
        for node in comp:  # a cycle through every member not yet on a reported one
            if node in covered:
                continue
            chain = _shortest_cycle(graph, node, members)
            covered.update(chain)
            i = chain.index(min(chain[:-1]))  # rotate: the same cycle reads the same way
            canon = tuple(chain[i:-1] + chain[:i])
            if canon in reported:
                continue
            reported.add(canon)
            ring = [*canon, canon[0]]
            where = ", ".join(f"{mods[a].rel}:{graph[a][b]} imports {b}" for a, b in pairwise(ring))
            first = ring[0]
            out.append(
                Violation("cycle", mods[first].rel, graph[first][ring[1]], f"{' -> '.join(ring)} ({where})")
            )
    return out


def check_services_imports(mods: dict[str, Module]) -> list[Violation]:
    """Only the composition root under ``hil/`` may import ``services``."""
    out = []
    for mod in mods.values():
        if not _under(mod.name, "hil") or mod.name == COMPOSITION_ROOT:
            continue
        for imp in mod.imports:
            if _under(imp.name, "services"):
                out.append(
                    Violation(
                        "no-services",
                        mod.rel,
                        imp.line,
                        f"{mod.name} imports {imp.name}: only {COMPOSITION_ROOT} may import services",
                    )
                )
    return out


def check_pure(mods: dict[str, Module]) -> list[Violation]:
    """The pure packages stay free of the bus, the clock, threads, processes and CAN I/O."""
    out = []
    for mod in mods.values():
        pure = next((p for p in PURE_PACKAGES if _under(mod.name, p)), None)
        if pure is None:
            continue
        banned = IMPURE_IMPORTS + (("can",) if any(_under(mod.name, p) for p in NO_PYTHON_CAN) else ())
        for imp in mod.imports:
            top = imp.name.split(".")[0]
            if imp.target is None and top in banned:
                out.append(
                    Violation(
                        "pure",
                        mod.rel,
                        imp.line,
                        f"{mod.name} imports {imp.name}: {pure} is pure and may not use {top}",
                    )
                )
    return out


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def layer_of(name: str, layers: dict[int, tuple[str, ...]] = LAYERS) -> int | None:
    """The layer of the longest matching prefix, None when no entry matches."""
    best: tuple[int, int] | None = None  # (prefix length, layer)
    for layer, prefixes in layers.items():
        for p in prefixes:
            hit = name == p if p in EXACT_ONLY else _under(name, p)
            if hit and (best is None or len(p) > best[0]):
                best = (len(p), layer)
    return None if best is None else best[1]


def check_layers(mods: dict[str, Module]) -> list[Violation]:
    """Imports go to the same layer or down, never up; every module has a layer."""
    out = []
    for mod in mods.values():
        mine = layer_of(mod.name)
        if mine is None:
            out.append(Violation("layer", mod.rel, 1, f"{mod.name} matches no entry of LAYERS: give it one"))
            continue
        for imp in mod.imports:
            if imp.target is None or imp.target == mod.name:
                continue
            theirs = layer_of(imp.target)
            if theirs is not None and theirs > mine:
                out.append(
                    Violation(
                        "layer",
                        mod.rel,
                        imp.line,
                        f"{mod.name} (layer {mine}) imports {imp.target} (layer {theirs}): "
                        "a module may import only its own layer or below",
                    )
                )
    return out


def _functions(
    body: Iterable[ast.stmt], prefix: str
) -> Iterable[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """Every function and method with its qualified name (``Class.method``, ``f.inner``)."""
    for node in body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield f"{prefix}{node.name}", node
            yield from _functions(node.body, f"{prefix}{node.name}.")
        elif isinstance(node, ast.ClassDef):
            yield from _functions(node.body, f"{prefix}{node.name}.")
        else:  # defs under if/try/with/for at any depth
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.stmt):
                    yield from _functions([child], prefix)


def check_function_length(mods: dict[str, Module], limit: int = MAX_FUNCTION_LINES) -> list[Violation]:
    """No function or method longer than ``limit`` lines (``def`` to its last line)."""
    out = []
    for mod in mods.values():
        for qualname, node in _functions(mod.tree.body, ""):
            n = (node.end_lineno or node.lineno) - node.lineno + 1
            if n > limit:
                out.append(
                    Violation(
                        "length",
                        mod.rel,
                        node.lineno,
                        f"{mod.name}.{qualname} is {n} lines (at most {limit}): split it",
                    )
                )
    return out


CHECKS = (check_cycles, check_services_imports, check_pure, check_layers, check_function_length)


def check_all(root: Path = REPO, packages: Sequence[str] = ROOT_PACKAGES) -> list[Violation]:
    mods = load_modules(root, packages)
    return [v for check in CHECKS for v in check(mods)]


if __name__ == "__main__":
    found = check_all()
    for v in found:
        print(v)
    raise SystemExit(1 if found else 0)
