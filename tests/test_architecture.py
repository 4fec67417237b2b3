"""Architecture guards for the ``jaxelastic`` package, read statically with :mod:`ast`.

* no import cycle between modules of ``jaxelastic`` (imports inside functions count; only
  imports under ``if TYPE_CHECKING:`` are ignored, they never run);
* no module takes a ``_private`` name (one leading underscore, not a dunder) of another
  module, neither by ``from .x import _name`` nor by attribute access ``x._name`` on an
  imported jaxelastic module (private *modules*, ``from . import _impl``, are fine: they are
  the package's own layout);
* no ``from x import *``;
* no function longer than :data:`MAX_FUNCTION_LINES` lines unless its docstring has a line
  starting with :data:`LONG_MARKER` followed by the reason;
* ``import jaxelastic`` never flips ``jax_enable_x64`` (checked in a fresh interpreter).

The import graph: ``import a.b.c`` and ``from a.b import c`` depend on module ``a.b.c``
(when it is one) else on the package ``a.b`` that defines the name. Importing a submodule
also runs every enclosing package ``__init__`` that is not an enclosing package of the
importer itself (those are already initialising), so such ``__init__`` files are
dependencies too; a package ``__init__`` depends on what it imports, its own submodules
included. A child importing a name from its own package ``__init__`` therefore closes a
cycle whenever that ``__init__`` imports the child.
"""

from __future__ import annotations

import ast
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "jaxelastic"
PKG_DIR = ROOT / PACKAGE

MAX_FUNCTION_LINES = 80
LONG_MARKER = "Long because:"


@dataclasses.dataclass(frozen=True)
class Import:
    """One import statement's effect: ``importer`` depends on ``target`` (a module name)."""

    importer: str
    target: str
    line: int
    text: str
    type_checking: bool


@dataclasses.dataclass
class Module:
    name: str
    path: Path
    is_pkg: bool
    source: str
    tree: ast.Module

    @property
    def rel(self) -> str:
        return self.path.relative_to(ROOT).as_posix()


def _module_name(path: Path) -> tuple[str, bool]:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    is_pkg = parts[-1] == "__init__"
    if is_pkg:
        parts = parts[:-1]
    return ".".join(parts), is_pkg


def _load_modules() -> dict[str, Module]:
    mods = {}
    for p in sorted(PKG_DIR.rglob("*.py")):
        name, is_pkg = _module_name(p)
        source = p.read_text(encoding="utf-8")
        mods[name] = Module(name, p, is_pkg, source, ast.parse(source, filename=str(p)))
    return mods


MODULES = _load_modules()


def _resolve(mod: Module, level: int, target: str | None) -> str:
    """Absolute module name of ``from <level dots><target> import ...`` inside ``mod``."""
    if level == 0:
        return target or ""
    base = mod.name.split(".") if mod.is_pkg else mod.name.split(".")[:-1]
    if level - 1 > len(base):
        raise ValueError(f"{mod.rel}: relative import beyond the top-level package")
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _in_package(name: str) -> bool:
    return name == PACKAGE or name.startswith(PACKAGE + ".")


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """``id`` of every node under an ``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            t = node.test
            name = (
                t.id if isinstance(t, ast.Name) else t.attr if isinstance(t, ast.Attribute) else ""
            )
            if name == "TYPE_CHECKING":
                for child in node.body:
                    out.update(id(n) for n in ast.walk(child))
    return out


def _ancestors(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


@dataclasses.dataclass
class Scan:
    imports: list[Import]
    private: list[str]
    star: list[str]


def _scan(mod: Module) -> Scan:
    """Imports of ``mod`` (with implicit package ``__init__`` dependencies), private-name
    imports and attribute accesses, and star imports."""
    imports: list[Import] = []
    private: list[str] = []
    star: list[str] = []
    guarded = _type_checking_nodes(mod.tree)
    own_ancestors = set(_ancestors(mod.name)) | ({mod.name} if mod.is_pkg else set())
    aliases: dict[str, str] = {}  # local name -> jaxelastic module it is bound to

    def depend(target: str, node: ast.stmt) -> None:
        text = ast.get_source_segment(mod.source, node) or ""
        tc = id(node) in guarded
        implicit = [t for t in _ancestors(target) if t not in own_ancestors]
        for t in [*implicit, target]:  # the target itself counts even if it is an ancestor
            if t in MODULES and t != mod.name:
                imports.append(Import(mod.name, t, node.lineno, text.splitlines()[0], tc))

    for node in ast.walk(mod.tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if not _in_package(a.name):
                    continue
                depend(a.name, node)
                if a.asname:
                    aliases[a.asname] = a.name
                else:
                    aliases[a.name.split(".")[0]] = PACKAGE
        elif isinstance(node, ast.ImportFrom):
            src = _resolve(mod, node.level, node.module)
            if any(a.name == "*" for a in node.names):
                star.append(f"{mod.rel}:{node.lineno}  from {src} import *")
            if not _in_package(src):
                continue
            for a in node.names:
                sub = f"{src}.{a.name}"
                if sub in MODULES:  # a submodule
                    depend(sub, node)
                    aliases[a.asname or a.name] = sub
                    continue
                depend(src, node)
                if _is_private(a.name) and src != mod.name:
                    private.append(f"{mod.rel}:{node.lineno}  {a.name}  (from {src})")
    for node in ast.walk(mod.tree):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id in aliases
            and _is_private(node.attr)
        ):
            owner = aliases[node.value.id]
            if f"{owner}.{node.attr}" not in MODULES and owner != mod.name:
                private.append(
                    f"{mod.rel}:{node.lineno}  {node.value.id}.{node.attr}  (of {owner})"
                )
    return Scan(imports, private, star)


SCANS = {name: _scan(m) for name, m in MODULES.items()}


def _strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm (iterative): components of more than one node, or self-loops."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
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
                if len(comp) > 1 or v in edges[v]:
                    out.append(sorted(comp))
    return out


def import_cycles() -> list[str]:
    """One message per cycle: its modules and the import lines that close it."""
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    where: dict[tuple[str, str], list[Import]] = {}
    for scan in SCANS.values():
        for imp in scan.imports:
            if imp.type_checking:
                continue
            edges[imp.importer].add(imp.target)
            where.setdefault((imp.importer, imp.target), []).append(imp)
    out = []
    for comp in _strongly_connected(edges):
        members = set(comp)
        lines = [f"cycle: {' <-> '.join(comp)}"]
        for (a, b), imps in sorted(where.items()):
            if a in members and b in members:
                imp = imps[0]
                more = f" (+{len(imps) - 1} more)" if len(imps) > 1 else ""
                lines.append(f"    {MODULES[a].rel}:{imp.line} -> {b}: {imp.text.strip()}{more}")
        out.append("\n".join(lines))
    return out


def _report(title: str, items: list[str]) -> str:
    return f"{len(items)} {title}:\n" + "\n".join(f"  {s}" for s in items)


def test_no_import_cycles():
    cycles = import_cycles()
    if cycles:
        pytest.fail(_report("import cycles between jaxelastic modules", cycles), pytrace=False)


def test_no_private_names_from_other_modules():
    bad = [s for scan in SCANS.values() for s in scan.private]
    title = "private names taken from another jaxelastic module"
    if bad:
        pytest.fail(_report(title, bad), pytrace=False)


def test_no_star_imports():
    bad = [s for scan in SCANS.values() for s in scan.star]
    if bad:
        pytest.fail(_report("star imports", bad), pytrace=False)


def long_functions() -> list[str]:
    """Functions over the line limit whose docstring gives no reason."""
    out = []
    for mod in MODULES.values():
        for node in ast.walk(mod.tree):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            n = (node.end_lineno or node.lineno) - node.lineno + 1
            if n <= MAX_FUNCTION_LINES:
                continue
            doc = ast.get_docstring(node) or ""
            reasons = [
                ln.strip()[len(LONG_MARKER) :].strip()
                for ln in doc.splitlines()
                if ln.strip().startswith(LONG_MARKER)
            ]
            if not any(reasons):
                out.append(f"{mod.rel}:{node.lineno}  {node.name}  ({n} lines)")
    return out


def test_long_functions_say_why():
    bad = long_functions()
    title = (
        f"functions over {MAX_FUNCTION_LINES} lines without a docstring line "
        f"'{LONG_MARKER} <reason>' (split them by concept, or give the reason)"
    )
    if bad:
        pytest.fail(_report(title, bad), pytrace=False)


def test_checks_see_the_package():
    # guard the guards: a wrong root would make every check above pass vacuously
    assert PACKAGE in MODULES and f"{PACKAGE}.io" in MODULES
    assert sum(len(s.imports) for s in SCANS.values()) > 20


def test_scanner_catches_violations(tmp_path, monkeypatch):
    """The checks flag synthetic cycles (one through a function-level import, one through the
    package ``__init__``), a private import, an attribute access and a star import, and
    ignore TYPE_CHECKING imports."""
    src = {
        "__init__.py": "from .a import f\nfrom . import e\n",
        "a.py": "def f():\n    from . import b\n    return b._hidden\n",
        "b.py": "from .a import f\nfrom .c import _g\nfrom os.path import *\n",
        "c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .d import X\n"
        "def _g():\n    pass\n",
        "d.py": "from .c import _g as g\n",
        "e.py": "def h():\n    import jaxelastic as je\n\n    return je.f\n",
    }
    pkg = tmp_path / PACKAGE
    pkg.mkdir()
    for k, v in src.items():
        (pkg / k).write_text(v)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PKG_DIR", pkg)
    mods = _load_modules()
    monkeypatch.setattr(sys.modules[__name__], "MODULES", mods)
    scans = {n: _scan(m) for n, m in mods.items()}
    monkeypatch.setattr(sys.modules[__name__], "SCANS", scans)
    cycles = import_cycles()
    heads = sorted(c.splitlines()[0] for c in cycles)
    assert heads == [
        "cycle: jaxelastic <-> jaxelastic.e",  # through the package's own __init__
        "cycle: jaxelastic.a <-> jaxelastic.b",  # through a function-level import
    ], cycles
    private = sorted(s for sc in scans.values() for s in sc.private)
    assert [p.split()[1] for p in private] == ["b._hidden", "_g", "_g"], private
    assert [s.split(":")[0] for sc in scans.values() for s in sc.star] == ["jaxelastic/b.py"]


def test_import_does_not_flip_x64():
    code = (
        "import jax\n"
        "before = bool(jax.config.jax_enable_x64)\n"
        "import jaxelastic\n"
        "after = bool(jax.config.jax_enable_x64)\n"
        "assert before is False, 'x64 already on before the import'\n"
        "assert after == before, f'import jaxelastic flipped jax_enable_x64 to {after}'\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env.setdefault("JAX_PLATFORMS", "cpu")
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]


if __name__ == "__main__":  # pragma: no cover - a quick listing without pytest
    for title, items in (
        ("import cycles", import_cycles()),
        ("private imports", [s for sc in SCANS.values() for s in sc.private]),
        ("star imports", [s for sc in SCANS.values() for s in sc.star]),
        ("long functions", long_functions()),
    ):
        print(_report(title, items))
