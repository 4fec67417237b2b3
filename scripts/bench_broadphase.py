"""Self-contact broad phase cost: the host spatial hash at ~5k-80k triangles.

A triangulated sheet folded into two parallel layers 0.01 (relative) apart, so many
pairs are in reach; radius = d̂ + 2·margin with d̂ = 1e-3 × diagonal and margin = min(10 d̂, ¼ mean
edge length) (the defaults). Prints a table (min of 3) and writes JSON (``--out``).

    .venv/bin/python scripts/bench_broadphase.py [--out out/bench/broadphase.json]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from jaxelastic.contact.broadphase import Surface, candidate_pairs
from jaxelastic.io import write_json


def folded_sheet(n: int):
    """Two n×n-quad layers (4n² triangles) of the unit square, 0.01 apart in z."""
    g = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    layer = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    pts = np.concatenate([layer, layer + [0.0, 0.0, 0.01]])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    faces = np.concatenate([tri, tri + (n + 1) ** 2]).astype(np.int32)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(e, axis=1), axis=0).astype(np.int32)
    nodes = np.arange(len(pts), dtype=np.int32)
    return pts, Surface(3, faces, edges, nodes)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/bench/broadphase.json")
    ap.add_argument("--sizes", default="25,50,71,100")
    args = ap.parse_args()
    rows = []
    print(f"{'triangles':>10} {'edges':>8} {'pt pairs':>10} {'ee pairs':>10} {'time [s]':>9}")
    for n in (int(s) for s in args.sizes.split(",")):
        x, surf = folded_sheet(n)
        diag = float(np.linalg.norm(x.max(0) - x.min(0)))
        dhat = 1e-3 * diag
        e = x[surf.edges[:, 1]] - x[surf.edges[:, 0]]
        margin = min(10 * dhat, 0.25 * float(np.mean(np.linalg.norm(e, axis=1))))
        r = dhat + 2 * margin  # the defaults of make_self_contact
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            pt, ee = candidate_pairs(x, surf, r)
            times.append(time.perf_counter() - t0)
        row = dict(
            triangles=len(surf.faces),
            edges=len(surf.edges),
            pt_pairs=len(pt),
            ee_pairs=len(ee),
            radius=r,
            time_s=min(times),
        )
        rows.append(row)
        print(
            f"{row['triangles']:>10} {row['edges']:>8} {row['pt_pairs']:>10} "
            f"{row['ee_pairs']:>10} {row['time_s']:>9.3f}"
        )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {rss:.0f} MB")
    write_json(args.out, dict(rows=rows, peak_rss_mb=rss))


if __name__ == "__main__":
    main()
