"""Write the shipped scene ``fit_plate_hole``'s mesh and its synthetic measurements.

A rubber plate with a central hole (one eighth by symmetry: half-width 20 mm, hole radius
5 mm, half-thickness 1 mm) is pulled 3 mm along x in six levels. The "experiment" is the
same test solved on a finer P2 mesh (``plate_with_hole(12, 6, 2, order=2)``) of a
Mooney–Rivlin material, c10 = 0.15 MPa, c01 = 0.05 MPa, κ = 20 MPa, observed with 1 %
Gaussian noise (σ = 1 % of each signal's RMS): the support force on the gripped edge
(``fit_plate_hole_force.csv``, header ``factor,force``) and the in-plane displacements of
24 random points of the top face (``fit_plate_hole_dic.npz``: ``points`` (24, 3) rest
coordinates, ``displacements`` (6, 24, 3), z set to 0: an in-plane DIC system does not
see it). The scene identifies on the coarser P2 mesh ``plate_with_hole(6, 3, 1,
order=2)`` (``fit_plate_hole.vtu``). The σ of each observation is written into the scene
file by hand from this script's output.

    .venv/bin/python scripts/make_fit_plate_hole.py [--out jaxelastic/scene/data]
"""

from __future__ import annotations

import argparse
import pathlib

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxelastic as je  # noqa: E402
from jaxelastic import fitting as F  # noqa: E402
from jaxelastic import materials as M  # noqa: E402
from jaxelastic.fitting import specimens as S  # noqa: E402
from jaxelastic.io import write_vtu  # noqa: E402

GEOMETRY = dict(half_width=0.02, radius=0.005, half_thickness=0.001)  # [m]
PULL = 0.003  # [m]
FACTORS = np.linspace(1 / 6, 1.0, 6)
TRUTH = M.MooneyRivlin(c10=1.5e5, c01=5.0e4, kappa=2.0e7)  # [Pa]
N_POINTS, NOISE, SEED = 24, 0.01, 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="jaxelastic/scene/data", help="output directory")
    args = ap.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    fine = S.hole_test(S.plate_with_hole(12, 6, 2, order=2, **GEOMETRY), PULL)
    model = S.plate_with_hole(6, 3, 1, order=2, **GEOMETRY)
    dic = S.dic_points(fine, N_POINTS, seed=SEED, margin=0.002)
    pot = je.Potential(fine.mesh, TRUTH, psi=M.mooney_rivlin)
    _, data = S.synthetic_measurements(fine, pot, FACTORS, dic, NOISE, SEED + 1, F.FIT_SOLVER)

    write_vtu(str(out / "fit_plate_hole.vtu"), model)
    lines = ["factor,force"] + [
        f"{f:.17g},{v:.17g}" for f, v in zip(FACTORS, data["force"], strict=True)
    ]
    (out / "fit_plate_hole_force.csv").write_text("\n".join(lines) + "\n")
    u = np.zeros((len(FACTORS), N_POINTS, 3))
    u[..., :2] = data["displacements"]
    np.savez(out / "fit_plate_hole_dic.npz", points=dic, displacements=u)
    print(f"model mesh: {model.n_nodes} nodes, {model.n_cells} cells ({model.element})")
    print(f"force [N] per level: {np.array2string(data['force'], precision=5)}")
    print(f"sigma of the force: {data['sigma_force']:.6g} N")
    print(f"sigma of the DIC displacements: {data['sigma_u']:.6g} m")


if __name__ == "__main__":
    main()
