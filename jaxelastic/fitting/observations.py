"""Observed positions: the misfit measure, synthetic noise, marker nodes and nested meshes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["observation_loss", "add_noise", "choose_markers", "nested_nodes"]


def observation_loss(x, observed, reference, nodes=None):
    """Relative squared misfit of observed positions (one load case or time step).

    ``‖x[nodes] − observed‖² / ‖observed − reference[nodes]‖²``: 1 for the rest shape,
    0 for a perfect fit, so cases with different load magnitudes weigh alike.

    Args:
        x: ``(n_nodes, dim)`` computed positions.
        observed: ``(n_obs, dim)`` observed positions (``n_obs = n_nodes`` if nodes is None).
        reference: ``(n_nodes, dim)`` rest positions.
        nodes: ``(n_obs,)`` int marker-node indices, or None for all nodes.
    """
    if nodes is not None:
        x, reference = x[nodes], reference[nodes]
    return jnp.sum((x - observed) ** 2) / jnp.sum((observed - reference) ** 2)


def add_noise(observed, reference, rel, key):
    """Observed positions with i.i.d. Gaussian noise on every component.

    ``σ = rel × RMS displacement``, ``RMS displacement = sqrt(mean_a ‖observed_a −
    reference_a‖²)`` over the observed nodes a; each coordinate gets ``N(0, σ²)``.

    Args:
        observed: ``(n_obs, dim)`` positions; reference: ``(n_obs, dim)`` rest positions
            of the same nodes; rel: relative noise level (0.01 = 1 %); key: PRNG key.
    """
    observed = jnp.asarray(observed)
    u = observed - jnp.asarray(reference)
    sigma = rel * jnp.sqrt(jnp.mean(jnp.sum(u * u, axis=-1)))
    return observed + sigma * jax.random.normal(key, observed.shape, observed.dtype)


def choose_markers(mask, fraction: float, seed: int, candidates=None) -> np.ndarray:
    """Sorted random marker nodes: ``max(1, round(fraction·n_nodes))`` of the nodes that are
    not fully prescribed and, if given, in ``candidates``; all such nodes when
    ``fraction ≥ 1``.

    Args:
        mask: ``(n_nodes, dim)`` bool Dirichlet mask; fraction: share of all nodes;
        seed: NumPy random seed; candidates: optional node indices to draw from.
    """
    mask = np.asarray(mask)
    n = mask.shape[0]
    ok = ~mask.all(axis=1)
    if candidates is not None:
        sel = np.zeros(n, bool)
        sel[np.asarray(candidates)] = True
        ok &= sel
    pool = np.flatnonzero(ok)
    if fraction >= 1.0:
        return pool
    k = min(pool.size, max(1, int(round(fraction * n))))
    return np.sort(np.random.default_rng(seed).choice(pool, size=k, replace=False))


def nested_nodes(fine_points, coarse_points, tol: float = 1e-9) -> np.ndarray:
    """Index of each coarse node among the fine nodes at the same rest position.

    Args:
        fine_points: ``(n_fine, dim)``; coarse_points: ``(n_coarse, dim)`` rest positions.
        tol: relative to the bounding-box diagonal.
    Returns:
        ``(n_coarse,)`` int indices into the fine mesh.
    Raises:
        ValueError: a coarse node has no fine node at its position (not a nested mesh).
    """
    # cKDTree comes from the compiled scipy.spatial._ckdtree, which has no stubs
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

    fine, coarse = np.asarray(fine_points), np.asarray(coarse_points)
    d, idx = cKDTree(fine).query(coarse)
    diag = float(np.linalg.norm(np.ptp(fine, axis=0)))
    if d.size and d.max() > tol * max(diag, 1e-300):
        raise ValueError(
            f"meshes are not nested: a coarse node is {d.max():.3g} from any fine node"
        )
    return idx.astype(np.int64)
