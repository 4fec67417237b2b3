"""Helpers shared by ``report_accuracy.py`` and ``report_stability.py`` (not a library module).

Atomic output files (on :func:`jaxelastic.io.write_atomic`), the machine description
stamped on every plot, Pareto fronts, rates, and the element variants (P1, P2, F-bar) as
mesh-generator keywords. The problems themselves are in :mod:`jaxelastic.verification`.
"""

from __future__ import annotations

import csv
import io
import os
import platform
from pathlib import Path

import numpy as np

from jaxelastic import io as jio
from jaxelastic.io import write_atomic

# element variant -> keyword arguments of the mesh generators (rectangle, box, cook_membrane)
ELEMENT_KW = {
    "P1": {},
    "P2": dict(order=2),
    "P2-Fbar": dict(order=2, formulation="fbar"),
    "P1-Fbar": dict(order=1, formulation="fbar"),
    "P2-Bbar": dict(order=2, formulation="bbar"),
    "P1-Bbar": dict(order=1, formulation="bbar"),
}
ELEMENT_NOTES = {
    "P1": "linear triangles/tets (tri3/tet4)",
    "P2": "quadratic triangles/tets (tri6/tet10)",
    "P2-Fbar": "quadratic with F-bar (cell-averaged J)",
    "P1-Fbar": "composite P1 (4/8 sub-simplices per P2 cell) with F-bar",
    "P2-Bbar": "quadratic with small-strain B-bar (for the linear material)",
    "P1-Bbar": "composite P1 with small-strain B-bar (for the linear material)",
}


class Unavailable(RuntimeError):
    """An element variant a case is not defined for (the row is skipped, with the reason)."""


def element_kw(element: str) -> dict:
    """Mesh-generator keywords (``order``, ``formulation``) of an element variant."""
    if element not in ELEMENT_KW:
        raise ValueError(f"element must be one of {sorted(ELEMENT_KW)}, got {element!r}")
    return dict(ELEMENT_KW[element])


def machine() -> str:
    """One line naming the machine (cores, CPU, OS, jax) for plots and JSON."""
    import jax

    cpu = platform.processor() or platform.machine()
    return (
        f"{os.cpu_count()} cores ({cpu}), {platform.system()}, jax {jax.__version__}, "
        f"{jax.default_backend()}, float64"
    )


def write_text(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8, line endings as given) atomically to ``path``, creating its
    directory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = text.encode()

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    write_atomic(path, write)


def write_json(path: Path, obj) -> None:
    """Write ``obj`` as JSON (indent 1, NaN/inf as ``null``) atomically to ``path``,
    creating its directory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    jio.write_json(path, obj, indent=1, nonfinite="null")


def write_csv(path: Path, rows: list[dict]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and not isinstance(v, (dict, list))]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in keys})
    write_text(path, buf.getvalue())


def save_figure(fig, path: Path, dpi: int = 110) -> None:
    """Save ``fig`` as a PNG atomically to ``path``, creating its directory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight"))


def pareto(times, errors) -> np.ndarray:
    """Indices of the non-dominated points (no other point is both faster and more
    accurate), sorted by time."""
    t, e = np.asarray(times, float), np.asarray(errors, float)
    ok = np.flatnonzero(np.isfinite(t) & np.isfinite(e) & (e > 0))
    idx = ok[np.lexsort((e[ok], t[ok]))]
    front, best = [], np.inf
    for i in idx:
        if e[i] < best:
            front.append(i)
            best = e[i]
    return np.asarray(front, dtype=int)


def rate(h, err) -> float:
    """Least-squares slope of log(err) against log(h) (NaN with fewer than 2 points)."""
    h, err = np.asarray(h, float), np.asarray(err, float)
    ok = np.isfinite(h) & np.isfinite(err) & (err > 0) & (h > 0)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(h[ok]), np.log(err[ok]), 1)[0])
