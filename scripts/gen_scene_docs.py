"""Write ``docs/scenes.md``, the scene-file reference, from the scene schema.

Usage (from the project root): ``python scripts/gen_scene_docs.py [--check]``; ``--check``
only compares and exits 1 when the committed file is out of date.
"""

from __future__ import annotations

import argparse
import os
import sys

from jaxelastic.io import write_atomic
from jaxelastic.scene import reference_markdown

PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir, "docs", "scenes.md")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="compare only; exit 1 if stale")
    args = p.parse_args(argv)
    text = reference_markdown()
    path = os.path.normpath(PATH)
    if args.check:
        with open(path, encoding="utf-8") as f:
            same = f.read() == text
        print(f"{path}: {'up to date' if same else 'out of date'}")
        return 0 if same else 1

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)

    write_atomic(path, write)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
