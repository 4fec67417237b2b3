"""README.md is the entry point: the two set-up commands first, short, its links resolve.

Its Python example is executed by ``tests/test_docs.py`` (with every docs page).
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TEXT = README.read_text(encoding="utf-8")

# .ci/run runs the second command verbatim; the first is what a new user types
SETUP = (
    "python3 -m venv .venv && .venv/bin/pip install -q -e '.[all,dev]' && "
    ".venv/bin/python -m jaxelastic run --out out/default",
    "python3 -m venv .venv && .venv/bin/pip install -q -e '.[all,dev]' && "
    ".venv/bin/python -m pytest -q",
)


def test_starts_with_the_two_setup_commands():
    blocks = re.findall(r"```(\w*)\n(.*?)```", TEXT, flags=re.S)
    assert [lang for lang, _ in blocks[:2]] == ["bash", "bash"]
    assert [code.strip() for _, code in blocks[:2]] == list(SETUP)
    before = TEXT[: TEXT.index("```")]
    assert before.strip() == "# jaxelastic", "nothing but the title before the two commands"


def test_is_an_entry_point():
    lines = TEXT.splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines (at most 150)"
    assert len(re.findall(r"```python\n", TEXT)) == 1, "one complete example"
    for heading in ("## Example", "## Features", "## Benchmark", "## Documentation"):
        assert heading in lines, heading


def test_links_resolve():
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", TEXT)
    local = [link for link in links if not re.match(r"[a-z]+://", link)]
    assert any(link.startswith("docs/") for link in local)
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, f"README links to missing files: {missing}"
