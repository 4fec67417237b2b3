"""mkdocs hooks for the jaxelastic site (listed under ``hooks:`` in ``mkdocs.yml``).

* The notebooks are executed at build time by mkdocs-jupyter through the ``python3`` kernel.
  A throw-away kernel spec of that name, whose command is the interpreter running mkdocs,
  goes first on ``JUPYTER_PATH`` (as in ``tests/test_notebooks.py``), so the kernel is the
  project's venv however mkdocs was started (``.venv/bin/mkdocs build`` without activating
  the venv) and whatever kernels are installed per user.
* Docstrings are written with Sphinx roles (``:func:`~jaxelastic.solve```); mkdocstrings
  renders them as Markdown, so the role prefix is dropped and ``~a.b.c`` shortened to ``c``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
import tempfile

_ROLE = re.compile(r":(?:func|class|meth|mod|attr|data|exc|obj|py:\w+):(?=<code>)")
_TILDE = re.compile(r"<code>~(?:[\w]+\.)*([\w]+(?:\(\))?)</code>")
_KERNEL_DIR: list[str] = []


def on_config(config, **kwargs):
    data = tempfile.mkdtemp(prefix="jaxelastic-docs-jupyter-")
    _KERNEL_DIR.append(data)
    spec_dir = os.path.join(data, "kernels", "python3")
    os.makedirs(spec_dir)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (jaxelastic docs)",
        "language": "python",
    }
    with open(os.path.join(spec_dir, "kernel.json"), "w", encoding="utf-8") as f:
        json.dump(spec, f)
    os.environ["JUPYTER_PATH"] = os.pathsep.join(
        p for p in (data, os.environ.get("JUPYTER_PATH", "")) if p
    )
    return config


def on_page_content(html, **kwargs):
    return _TILDE.sub(r"<code>\1</code>", _ROLE.sub("", html))


def on_shutdown(**kwargs):
    while _KERNEL_DIR:
        shutil.rmtree(_KERNEL_DIR.pop(), ignore_errors=True)
