"""The repository speaks only of the project: no development-round, ticket or team words.

README, docs, library, tests, scripts, notebooks and CI say what is true of jaxelastic
now. A figure from a past run carries its date, machine, command and commit, not the
round of work that produced it (a session or issue number, "the lead's figure").
The test reads every text file under those paths and names each offending line as
``path:line``.
"""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROOTS = (
    "README.md",
    "docs",
    "jaxelastic",
    "tests",
    "scripts",
    "notebooks",
    ".ci",
    "mkdocs.yml",
    "pyproject.toml",
)
TEXT_SUFFIXES = {".py", ".md", ".ipynb", ".toml", ".yml", ".yaml", ".sh", ".txt", ".cfg", ".json"}
NO_SUFFIX = {"run"}  # .ci/run
SKIP_DIRS = {"__pycache__", ".ipynb_checkpoints"}

# case-insensitive; each alternative names a development round, a ticket or a team role,
# and none matches ordinary prose ("issue a warning", "a Python session", "round-off",
# "AMG's lead grows", "the test session's cache")
WORDS = re.compile(
    r"""(?ix)
      \bsessions?[\s-]+\#?\d+                     # session N, sessions N-M, session-N
    | \b(?:this|that|last|previous|earlier|next|same|later|another|other)\s+session\b
    | \bsession[\s-](?:start|end)\b               # the session-start code
    | \bissues?[\s-]+\#?\d+                       # issue N, issue #N
    | \btickets?\b
    | \bstop\s+\#?\d+                             # stop 25
    | \bhelper\s+[a-z]\d                          # helper B2
    | \bre-?design                                # before the redesign
    | \bsprints?\b
    | \bround\s+\#?\d+                            # round 3
    | \bmilestones?\b
    | \bthe\s+lead\b(?!\s+(?:time|of|over)\b) | \blead's\b
    | \bissue's\b | \b(?:of|in|by)\s+the\s+issue\b      # the issue's target
    | \bthe\s+issue\s+(?:started|demands|asks|asked|wants|targets)\b
    """
)


def _files(name):
    path = ROOT / name
    if path.is_file():
        yield path
    elif path.is_dir():
        for f in sorted(path.rglob("*")):
            if (
                f.is_file()
                and not f.is_symlink()  # docs/notebooks is a link to notebooks/
                and (f.suffix in TEXT_SUFFIXES or f.name in NO_SUFFIX)
                and not SKIP_DIRS.intersection(f.parts)
                and f.resolve() != Path(__file__).resolve()
            ):
                yield f


@pytest.mark.parametrize("name", ROOTS)
def test_no_development_history_words(name):
    hits = []
    for f in _files(name):
        try:
            text = f.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue
        for i, line in enumerate(text.splitlines(), 1):
            m = WORDS.search(line)
            if m:
                hits.append(f"{f.relative_to(ROOT)}:{i}: {m.group(0)!r}: {line.strip()[:120]}")
    assert not hits, "development-history words (say date, machine, command, commit):\n" + (
        "\n".join(hits)
    )


def test_the_pattern_tells_history_from_prose():
    # the numbered examples are filled in below, so that this file itself passes the check
    history = (
        "measured in session {n}",
        "Sessions {n}–{m} cuts",
        "the session-9 code",
        "issue {k} targets",
        "(issue #{k})",
        "ticket 7",
        "stop 25",
        "helper B2",
        "before the redesign",
        "this sprint",
        "round 3 of review",
        "the lead's idle figure",
        "rerun by the lead",
        "found and fixed this session",
        "the issue's target",
        "the three cases of the issue",
        "the alternative the issue started from",
    )
    history = tuple(h.format(n=9, m=10, k=11) for h in history)
    prose = (
        "issue a warning",
        "issues one callback per step",
        "in a Python session nothing is cached",
        "the test session's persistent cache",
        "round-off floor",
        "rounded to 3 digits",
        "AMG's lead grows with size",
        "stop at the next iteration",
        "helpers shared by the reports",
        "a stop criterion",
        "the issue with a traced value is",
    )
    assert all(WORDS.search(s) for s in history), [s for s in history if not WORDS.search(s)]
    assert not any(WORDS.search(s) for s in prose), [s for s in prose if WORDS.search(s)]
