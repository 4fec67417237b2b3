"""Treloar's (1944) rubber data fitted by five hyperelastic laws through homogeneous tests.

Data: :mod:`jaxelastic.verification.treloar` (uniaxial, equibiaxial and pure-shear tension
of vulcanised natural rubber; stretch and nominal stress [MPa]). Models: Mooney–Rivlin,
Yeoh, Ogden (three terms), Gent and Arruda–Boyce (:mod:`jaxelastic.materials.rubber`), each
in the exactly incompressible limit (κ drops out), fitted by
:func:`jaxelastic.fitting.fit_curves` (Levenberg–Marquardt, relative weighting σ_i = |P_i|,
so the residuals are relative stress errors) to

* ``joint``: all three curves together, and
* ``uniaxial``: the uniaxial curve alone (then predicting the other two).

For each fit: the fitted constants with their Gauss–Newton standard errors (covariance
scaled by the reduced χ², since the σ are weights), the RMS relative stress error
``sqrt(mean(((P_model − P)/P)²))`` of each test type, the status, and the time of a fit
(first call, compilation included, and a second, warm call). Initial guesses: each law's
documented default constants (``<model>_params()``).

Writes ``report_treloar.json``, ``treloar_table.md`` (the Markdown table of the docs
page) and ``treloar.png`` (data against fitted curves) to ``--out``.

Usage::

    python scripts/report_treloar.py --out out/report_treloar
    python scripts/report_treloar.py --models mooney_rivlin,ogden --no-plot --out /tmp/t
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import _report_common as rc
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxelastic.materials as M  # noqa: E402
from jaxelastic.fitting import (  # noqa: E402
    Fixed,
    Free,
    Positive,
    fit_curves,
    nominal_stress,
    stress_curve,
)
from jaxelastic.verification import TRELOAR, TRELOAR_UNIAXIAL  # noqa: E402
from jaxelastic.verification.treloar import TRELOAR_CITATION  # noqa: E402

# law, initial constants, transforms (Free where a constant may be ≤ 0), label
MODELS = {
    "mooney_rivlin": (
        M.mooney_rivlin,
        M.mooney_rivlin_params(),
        M.MooneyRivlin(Free(), Free(), Fixed()),
        "Mooney–Rivlin",
    ),
    "yeoh": (M.yeoh, M.yeoh_params(), M.Yeoh(Free(), Free(), Free(), Fixed()), "Yeoh"),
    "ogden": (M.ogden, M.ogden_params(), M.Ogden(*[Free()] * 6, Fixed()), "Ogden (3 terms)"),
    "gent": (M.gent, M.gent_params(), M.Gent(Positive(), Positive(), Fixed()), "Gent"),
    "arruda_boyce": (
        M.arruda_boyce,
        M.arruda_boyce_params(),
        M.ArrudaBoyce(Positive(), Positive(), Fixed()),
        "Arruda–Boyce",
    ),
}
TEST_LABELS = {"uniaxial": "uniaxial", "equibiaxial": "equibiaxial", "pure_shear": "pure shear"}
FITS = {"joint": TRELOAR, "uniaxial": (TRELOAR_UNIAXIAL,)}


def _curves(data):
    return [stress_curve(c.test, c.stretch, c.stress) for c in data]


def fit_model(name: str, on: str) -> dict:
    """Fit one model to one data selection (cold, then warm) and evaluate every test type."""
    psi, init, transforms, _ = MODELS[name]
    curves = _curves(FITS[on])
    tic = time.perf_counter()
    fit_curves(psi, init, curves, transforms=transforms)
    cold = time.perf_counter() - tic
    tic = time.perf_counter()
    fit = fit_curves(psi, init, curves, transforms=transforms)
    warm = time.perf_counter() - tic
    rms = {}
    for c in TRELOAR:  # every test type, fitted or predicted
        pred = np.asarray(nominal_stress(psi, fit.params, c.test, c.stretch).stress)
        rms[c.test] = float(np.sqrt(np.mean(((pred - c.stress) / c.stress) ** 2)))
    return dict(
        model=name,
        fitted_on=on,
        converged=fit.converged,
        stop_reason=fit.result.stop_reason,
        iterations=fit.result.iterations,
        values=fit.values,
        standard_errors=fit.standard_errors,
        rms_relative_error=rms,
        time_first_s=cold,
        time_warm_s=warm,
        params=fit.params._asdict(),
    )


def _fmt_params(row: dict) -> str:
    se = row["standard_errors"]
    return ", ".join(f"{k} = {v:.4g} ± {se[k]:.2g}" for k, v in row["values"].items())


def table(rows: list[dict]) -> str:
    """The Markdown table: RMS relative error per test type, constants, status, time."""
    head = (
        "| model | fitted to | uniaxial | equibiaxial | pure shear | constants [MPa; α, J_m, λ_m "
        "dimensionless] ± standard error | status | warm fit [ms] |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        e = r["rms_relative_error"]
        cells = [
            MODELS[r["model"]][3],
            "all three" if r["fitted_on"] == "joint" else "uniaxial only",
            *(f"{100 * e[t]:.1f} %" for t in TEST_LABELS),
            _fmt_params(r),
            r["stop_reason"],
            f"{1e3 * r['time_warm_s']:.0f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path, stamp: str) -> None:
    """Data (markers) against the fitted curves: solid joint fits, dashed uniaxial-only."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 4.6))
    axs = fig.subplots(1, 3)
    colours = dict(zip(MODELS, ["C0", "C1", "C2", "C3", "C4"], strict=True))
    for ax, c in zip(axs, TRELOAR, strict=True):
        lam = np.linspace(1.0, float(c.stretch.max()) * 1.02, 200)
        ax.plot(c.stretch, c.stress, "ko", ms=4, label="Treloar (1944)")
        for r in rows:
            psi = MODELS[r["model"]][0]
            params = type(MODELS[r["model"]][1])(**r["params"])
            P = np.asarray(nominal_stress(psi, params, c.test, lam).stress)
            style = "-" if r["fitted_on"] == "joint" else "--"
            label = MODELS[r["model"]][3] + (
                " (joint)" if r["fitted_on"] == "joint" else " (uniax.)"
            )
            ax.plot(lam, P, style, color=colours[r["model"]], lw=1.3, label=label)
        ax.set_title(TEST_LABELS[c.test])
        ax.set_xlabel("stretch λ [-]")
        ax.set_ylabel("nominal stress P [MPa]")
        ax.set_ylim(0.0, 1.15 * float(c.stress.max()))
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=7, ncol=2)
    fig.suptitle(
        "Treloar's data and five incompressible laws: solid fitted to all three tests, dashed "
        f"to uniaxial only\n{stamp}",
        fontsize=9,
    )
    fig.tight_layout()
    rc.save_figure(fig, path)


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
        )
        return out.stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", default="out/report_treloar")
    ap.add_argument("--models", default=",".join(MODELS), help="comma-separated model names")
    ap.add_argument("--no-plot", action="store_true")
    a = ap.parse_args(argv)
    models = [m.strip() for m in a.models.split(",") if m.strip()]
    unknown = [m for m in models if m not in MODELS]
    if unknown or not models:
        ap.error(f"unknown model(s) {unknown}; choose from {list(MODELS)}")
    out = Path(a.out)
    rows = [fit_model(m, on) for m in models for on in FITS]
    md = table(rows)
    print(md)
    for r in rows:
        print(
            f"{r['model']:>13} {r['fitted_on']:>8}: {r['stop_reason']} in {r['iterations']} "
            f"iterations; first fit {r['time_first_s']:.2f} s (compilation included), warm "
            f"{1e3 * r['time_warm_s']:.1f} ms"
        )
    machine = rc.machine()
    stamp = (
        f"{time.strftime('%Y-%m-%d', time.gmtime())}, {machine}, commit {_commit()}; "
        "times measured on a loaded machine"
    )
    meta = dict(
        data=TRELOAR_CITATION,
        weighting="relative (sigma_i = |P_i|), covariance scaled by the reduced chi^2",
        incompressible=True,
        machine=machine,
        commit=_commit(),
        command="python " + " ".join([Path(sys.argv[0]).name, *(argv or sys.argv[1:])]),
        timing_note="measured on a loaded machine; first fit includes compilation",
    )
    rc.write_json(out / "report_treloar.json", dict(meta=meta, fits=rows))
    rc.write_text(out / "treloar_table.md", md)
    if not a.no_plot:
        plot(rows, out / "treloar.png", stamp)
    print(
        f"wrote {out}/report_treloar.json, treloar_table.md"
        + ("" if a.no_plot else ", treloar.png")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
