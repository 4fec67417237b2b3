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
* ``import jaxelastic`` never flips ``jax_enable_x64`` (checked in a fresh interpreter);
* data flows downhill: every module belongs to one of the ordered :data:`LAYERS` and imports
  only from its own layer or a lower one (imports under ``if TYPE_CHECKING:`` excepted);
* no module is named like a function, class or other name it defines or exports, and no
  package binds a name of one of its submodules to anything but that submodule;
* every module and every package ``__init__`` defines ``__all__``.

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


LAYERS: tuple[tuple[str, ...], ...] = (
    ("jaxelastic.deprecation", "jaxelastic.mesh", "jaxelastic.cache"),
    ("jaxelastic.mechanics",),
    ("jaxelastic.materials",),
    ("jaxelastic.loads", "jaxelastic.contact", "jaxelastic.parallel"),
    ("jaxelastic.postprocess",),
    ("jaxelastic.io", "jaxelastic.plot"),
    ("jaxelastic.solvers",),
    ("jaxelastic.dynamics", "jaxelastic.parallel.traffic"),
    ("jaxelastic.fitting",),
    ("jaxelastic.verification",),
    ("jaxelastic.scene",),
    ("jaxelastic.cli", "jaxelastic.__main__", "jaxelastic"),
)
"""The layers of the package, lowest first; each entry names modules or packages (a package
stands for every module under it, the most specific entry wins). A module may import only
from its own layer or a lower one.

The order is the import graph's: the mesh, and the forward of moved names
(:mod:`jaxelastic.deprecation`, which imports its targets by name on access), know nothing
above them; the mechanics kernels,
kinematics and the potential need only the mesh; the material laws use kinematics and the
parameter checks; loads, contact and the parallel layout build on the potential;
post-processing uses the loads' facet geometry, and the VTU writer the post-processing;
the solvers minimise potentials (contact terms, sharded meshes included); dynamics, and the
communication count of :mod:`jaxelastic.parallel.traffic` (which compiles solver kernels),
sit on the solvers; fitting differentiates static and dynamic solves; the benchmarks and the
cross-check are built from the layers below; scenes use everything, the command line runs
scenes and the cross-check, and the package ``__init__`` re-exports the lot."""


def layer_of(name: str) -> int | None:
    """Index in :data:`LAYERS` of module ``name`` (its most specific entry), or None."""
    best, depth = None, -1
    for i, entries in enumerate(LAYERS):
        for entry in entries:
            if (name == entry or name.startswith(entry + ".")) and entry.count(".") > depth:
                if name != entry and entry == PACKAGE:
                    continue  # the root entry is the package __init__ only
                best, depth = i, entry.count(".")
    return best


def layer_violations() -> list[str]:
    """Modules in no layer, and imports of a higher layer (TYPE_CHECKING imports excepted)."""
    out = [f"{m.rel}: in none of LAYERS" for n, m in MODULES.items() if layer_of(n) is None]
    for name, scan in SCANS.items():
        here = layer_of(name)
        for imp in scan.imports:
            there = layer_of(imp.target)
            if imp.type_checking or here is None or there is None or there <= here:
                continue
            out.append(
                f"{MODULES[name].rel}:{imp.line}: {imp.text.strip()}  (layer {here} "
                f"{LAYERS[here][0]} imports layer {there} {LAYERS[there][0]})"
            )
    return out


def test_layers_import_downhill():
    bad = layer_violations()
    if bad:
        title = "imports against the layer order (tests/test_architecture.py LAYERS)"
        pytest.fail(_report(title, bad), pytrace=False)


def _bound_names(tree: ast.Module) -> dict[str, list[ast.stmt]]:
    """Module-level name → the statements that bind it (defs, classes, assignments,
    imports; inside ``if``/``try`` blocks too, not inside functions or classes)."""
    out: dict[str, list[ast.stmt]] = {}

    def visit(body):
        for node in body:
            names: list[str] = []
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names = [node.name]
            elif isinstance(node, ast.Assign):
                names = [n.id for t in node.targets for n in ast.walk(t) if isinstance(n, ast.Name)]
            elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(
                node.target, ast.Name
            ):
                names = [node.target.id]
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [(a.asname or a.name).split(".")[0] for a in node.names]
            elif isinstance(node, (ast.If, ast.Try, ast.With)):
                for block in ("body", "orelse", "finalbody", "handlers"):
                    for part in getattr(node, block, []):
                        visit(part.body if isinstance(part, ast.ExceptHandler) else [part])
            for n in names:
                out.setdefault(n, []).append(node)

    visit(tree.body)
    return out


def _dunder_all(tree: ast.Module) -> list[str] | None:
    """The names of the module's ``__all__`` (None when it has none)."""
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
        if isinstance(node, (ast.Assign, ast.AnnAssign)) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in targets
        ):
            value = node.value
            if value is None:
                return []
            return [e.value for e in getattr(value, "elts", []) if isinstance(e, ast.Constant)]
    return None


def _binds_submodule(node: ast.stmt, pkg: Module, sub: str) -> bool:
    """Whether ``node`` of package ``pkg``'s ``__init__`` binds ``sub`` to the submodule."""
    if isinstance(node, ast.ImportFrom):
        src = _resolve(pkg, node.level, node.module)
        return src == pkg.name and any(
            a.name == sub and (a.asname or a.name) == sub for a in node.names
        )
    return False


def naming_violations() -> list[str]:
    """Modules named like a name they bind or export, and package attributes that shadow
    a submodule."""
    out = []
    for name, mod in MODULES.items():
        short = name.rsplit(".", 1)[-1]
        bound = _bound_names(mod.tree)
        exported = _dunder_all(mod.tree) or []
        if not mod.is_pkg and (short in bound or short in exported):
            out.append(f"{mod.rel}: module {short!r} also defines or exports {short!r}")
        if mod.is_pkg:
            for sub_name in MODULES:
                if sub_name.rsplit(".", 1)[0] != name:
                    continue
                sub = sub_name.rsplit(".", 1)[-1]
                others = [n for n in bound.get(sub, []) if not _binds_submodule(n, mod, sub)]
                if others:
                    out.append(
                        f"{mod.rel}: {name}.{sub} is bound to something other than the "
                        f"submodule (line {others[0].lineno})"
                    )
    return out


def missing_dunder_all() -> list[str]:
    return [f"{m.rel}: no __all__" for m in MODULES.values() if _dunder_all(m.tree) is None]


KNOWN_EXCEPTIONS: set[str] = set()
"""Violations of the naming and ``__all__`` rules that are known and waiting for their fix
(compared without the line number); an entry that no longer applies fails
:func:`test_known_exceptions_still_apply`."""


def _key(msg: str) -> str:
    return msg.split(" (line ")[0]


def test_no_module_named_like_what_it_defines():
    bad = [m for m in naming_violations() if _key(m) not in KNOWN_EXCEPTIONS]
    if bad:
        title = "modules named like a name they define, or package names shadowing a submodule"
        pytest.fail(_report(title, bad), pytrace=False)


def test_every_module_has_dunder_all():
    bad = [m for m in missing_dunder_all() if m not in KNOWN_EXCEPTIONS]
    if bad:
        pytest.fail(_report("modules without __all__", bad), pytrace=False)


def test_known_exceptions_still_apply():
    found = {_key(m) for m in naming_violations() + missing_dunder_all()}
    stale = sorted(KNOWN_EXCEPTIONS - found)
    if stale:
        title = "KNOWN_EXCEPTIONS that no longer apply (remove them)"
        pytest.fail(_report(title, stale), pytrace=False)


def test_layer_and_naming_checks_catch_violations(tmp_path, monkeypatch):
    """Synthetic package: an import uphill, a module in no layer, a self-named module, a
    shadowed submodule and a missing ``__all__`` are all found; a package re-exporting its
    submodule by name is not a violation."""
    src = {
        "__init__.py": "from . import low as low\nfrom .high import high as high\n__all__ = []\n",
        "low.py": "def f():\n    from . import high\n__all__ = ['f']\n",
        "high.py": "def high():\n    pass\n__all__ = ['high']\n",
        "stray.py": "x = 1\n",
    }
    pkg = tmp_path / PACKAGE
    pkg.mkdir()
    for k, v in src.items():
        (pkg / k).write_text(v)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PKG_DIR", pkg)
    mods = _load_modules()
    monkeypatch.setattr(sys.modules[__name__], "MODULES", mods)
    monkeypatch.setattr(sys.modules[__name__], "SCANS", {n: _scan(m) for n, m in mods.items()})
    layers = ((f"{PACKAGE}.low",), (f"{PACKAGE}.high",), (PACKAGE,))
    monkeypatch.setattr(sys.modules[__name__], "LAYERS", layers)
    layer = layer_violations()
    assert any("stray.py: in none of LAYERS" in v for v in layer), layer
    assert any(v.startswith(f"{PACKAGE}/low.py:2") for v in layer), layer
    names = naming_violations()
    assert any("module 'high' also defines" in v for v in names), names
    assert any(f"{PACKAGE}.high is bound" in v for v in names), names
    assert not any(f"{PACKAGE}.low is bound" in v for v in names), names
    assert missing_dunder_all() == [f"{PACKAGE}/stray.py: no __all__"]


def _fresh_python(code: str) -> subprocess.CompletedProcess:
    """``code`` run by a fresh interpreter on the CPU, without the JAX_* variables of the
    test run's environment (x64 among them)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["JAX_PLATFORMS"] = "cpu"
    return subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )


def test_import_does_not_flip_x64():
    code = (
        "import jax\n"
        "before = bool(jax.config.jax_enable_x64)\n"
        "import jaxelastic\n"
        "after = bool(jax.config.jax_enable_x64)\n"
        "assert before is False, 'x64 already on before the import'\n"
        "assert after == before, f'import jaxelastic flipped jax_enable_x64 to {after}'\n"
    )
    r = _fresh_python(code)
    assert r.returncode == 0, r.stderr[-3000:]


def test_import_starts_no_jax_runtime():
    """Importing every package runs no JAX computation and lists no device: a multi-process
    job must be able to call jax.distributed.initialize after ``import jaxelastic``."""
    code = (
        "import jax._src.xla_bridge as xb\n"
        "def refuse(*a, **k):\n"
        "    import traceback; traceback.print_stack()\n"
        "    raise SystemExit('the import started a JAX backend')\n"
        "xb.backends = refuse\n"
        "import jaxelastic, jaxelastic.cli, jaxelastic.scene, jaxelastic.fitting\n"
        "import jaxelastic.parallel, jaxelastic.verification, jaxelastic.dynamics\n"
    )
    r = _fresh_python(code)
    assert r.returncode == 0, r.stderr[-3000:]


if __name__ == "__main__":  # pragma: no cover - a quick listing without pytest
    for title, items in (
        ("import cycles", import_cycles()),
        ("private imports", [s for sc in SCANS.values() for s in sc.private]),
        ("star imports", [s for sc in SCANS.values() for s in sc.star]),
        ("long functions", long_functions()),
        ("layer violations", layer_violations()),
        ("naming violations", naming_violations()),
        ("modules without __all__", missing_dunder_all()),
    ):
        print(_report(title, items))


@pytest.mark.parametrize("package", ["jaxelastic", "jaxelastic.scene"])
def test_the_lazy_package_names_are_the_typed_ones_and_all_of_them(package):
    """A lazy package's ``__init__.py`` names its public API three times — the imports
    under ``if TYPE_CHECKING:`` (for type checkers and the API docs), the lazy table
    ``_LAZY`` (what runs) and ``__all__`` —: the three agree, and each lazy entry resolves
    to the object the typed import names."""
    import importlib

    pkg = importlib.import_module(package)
    path = ROOT / package.replace(".", "/") / "__init__.py"
    tree = ast.parse(path.read_text(encoding="utf-8"))
    typed: dict[str, tuple[str, str | None]] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom), ast.dump(imp)
                where = "." * imp.level + (imp.module or "")
                for alias in imp.names:
                    name = alias.asname or alias.name
                    typed[name] = (
                        (where + alias.name, None) if imp.module is None else (where, alias.name)
                    )
    lazy = pkg._LAZY  # the table itself, as the package defines it
    assert set(typed) == set(lazy), set(typed) ^ set(lazy)
    for name, expect in typed.items():
        assert tuple(lazy[name]) == expect, (name, lazy[name], expect)
        module = importlib.import_module(expect[0], package)
        obj = module if expect[1] is None else getattr(module, expect[1])
        assert getattr(pkg, name) is obj, name
    assert set(pkg.__all__) <= set(lazy) | set(vars(pkg)), set(pkg.__all__) - set(lazy)
