"""The code of README.md and of every documentation page runs, and every page is in the nav.

Convention (docs/index.md, "Building this site"): a fenced block whose info string is
``python`` is executed; the blocks of one page run in order in one namespace, in a
temporary working directory, with float64 enabled first (as the pages tell the reader to
do). A block marked ``py`` is highlighted the same way but not run (fragments, signatures);
``bash``/``toml``/``text`` blocks are not run. A page containing ``<!-- docs-test: slow -->``
is only run with ``-m slow``.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SLOW_MARK = "<!-- docs-test: slow -->"
# an opening fence ```python (optionally indented, e.g. inside a list; attributes such as
# title="..." allowed), up to the closing fence with the same indentation
BLOCK = re.compile(r"^([ \t]*)```python(?:[ \t][^\n]*)?\n(.*?)^\1```[ \t]*$", re.S | re.M)


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(line number, code)`` of each ```` ```python ```` block of a Markdown text."""
    out = []
    for m in BLOCK.finditer(text):
        line = text.count("\n", 0, m.start(2)) + 1
        out.append((line, textwrap.dedent(m.group(2))))
    return out


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def _params():
    params = []
    for path in _pages():
        text = path.read_text(encoding="utf-8")
        if not python_blocks(text):
            continue
        marks = [pytest.mark.slow] if SLOW_MARK in text else []
        params.append(pytest.param(path, marks=marks, id=str(path.relative_to(ROOT))))
    return params


def _check_readme(stdout: str) -> None:
    lines = stdout.splitlines()
    assert lines[0].startswith("SUCCESS"), stdout
    assert float(lines[1]) > 0, stdout  # stiffer beam sags less: d(lowest z)/dE > 0


CHECKS = {"README.md": _check_readme}


def test_blocks_found():
    """The extraction finds the README example and examples on the docs pages."""
    pages = {p.name for p in _pages() if python_blocks(p.read_text(encoding="utf-8"))}
    assert {"README.md", "getting-started.md", "materials.md"} <= pages, pages
    assert python_blocks("a\n```python\nx = 1\n```\n```py\ny = 2\n```\n") == [(3, "x = 1\n")]
    assert python_blocks("* item\n\n  ```python\n  x = 1\n  ```\n") == [(4, "x = 1\n")]
    assert python_blocks('```python title="a.py"\nx = 1\n```\n```pycon\n>>> 1\n```\n') == [
        (2, "x = 1\n")
    ]


@pytest.mark.extended
@pytest.mark.parametrize("path", _params())
def test_page_code_runs(path: Path, tmp_path, monkeypatch, capsys):
    import jax

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    x64 = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    name = str(path.relative_to(ROOT))
    namespace: dict = {"__name__": "__main__"}
    try:
        for line, code in python_blocks(path.read_text(encoding="utf-8")):
            try:
                exec(compile(code, f"{name}:{line}", "exec"), namespace)
            except Exception as e:
                raise AssertionError(
                    f"{name}: the python block at line {line} raised {type(e).__name__}: {e}"
                ) from e
    finally:
        jax.config.update("jax_enable_x64", x64)
    check = CHECKS.get(name)
    if check is not None:
        check(capsys.readouterr().out)


def _nav_entries() -> list[str]:
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    # mkdocs.yml uses mkdocs' !ENV tag; its value does not matter here
    Loader.add_constructor("!ENV", lambda loader, node: None)
    config = yaml.load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"), Loader=Loader)

    def walk(node):
        if isinstance(node, str):
            yield node
        elif isinstance(node, list):
            for item in node:
                yield from walk(item)
        elif isinstance(node, dict):
            for value in node.values():
                yield from walk(value)

    return list(walk(config["nav"]))


def test_every_page_is_in_the_nav():
    nav = _nav_entries()
    missing_files = [p for p in nav if not (DOCS / p).is_file()]
    assert not missing_files, f"nav entries without a file under docs/: {missing_files}"
    pages = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")}
    pages |= {f"notebooks/{p.name}" for p in (ROOT / "notebooks").glob("*.ipynb")}
    not_in_nav = sorted(pages - set(nav))
    assert not not_in_nav, f"pages missing from the nav of mkdocs.yml: {not_in_nav}"
