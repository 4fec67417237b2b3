"""Rigid obstacles as signed-distance functions: half-space, sphere, boxes, capsule, user SDF.

Every obstacle is a frozen pytree whose geometric parameters (and its friction coefficient
μ) are leaves, so gradients with respect to an obstacle's position or size come from
autodiff; an optional prescribed ``motion(t) -> (dim,)`` translation [m] (a static field)
moves it in time. The interface, for one point ``x`` ``(dim,)`` [m] at time ``t`` [s]:

* :meth:`distance` ``(x, t) -> ()``: signed distance [m], positive outside (the barrier's d);
* :meth:`toi` ``(x, p, t) -> ()``: the first fraction τ ≥ 0 of the step ``x → x + p`` at
  which the point reaches the obstacle's surface (+inf if it never does). Analytic for the
  half-space, sphere and boxes; conservative advancement (exact for a 1-Lipschitz SDF) for
  the capsule and user SDFs (:mod:`~jaxelastic.contact.ccd`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .ccd import conservative_toi, safe_norm

__all__ = [
    "HalfSpace",
    "Sphere",
    "Box",
    "RotatedBox",
    "Capsule",
    "SDF",
    "Obstacle",
    "check_obstacle",
    "interior_point",
    "NORMAL_LENGTHS",
]


@dataclasses.dataclass(frozen=True)
class _Moving:
    """Shared part: the prescribed translation and the default (conservative) CCD."""

    def offset(self, t) -> jax.Array:
        """The obstacle's translation at time t, ``(dim,)`` [m] (zero without motion)."""
        ref = self._ref()
        motion = getattr(self, "motion", None)
        if motion is None:
            return jnp.zeros_like(ref)
        return jnp.asarray(motion(t), ref.dtype).reshape(ref.shape)

    def _ref(self) -> jax.Array:  # a (dim,) leaf giving the dimension and dtype
        raise NotImplementedError

    def sdf(self, x: jax.Array) -> jax.Array:
        """Signed distance [m] of ``x`` ``(dim,)`` to the obstacle at rest (no motion)."""
        raise NotImplementedError

    def distance(self, x: jax.Array, t=0.0) -> jax.Array:
        """Signed distance [m] of ``x`` ``(dim,)`` at time ``t``; positive outside."""
        return self.sdf(x - self.offset(t))

    def toi(self, x: jax.Array, p: jax.Array, t=0.0) -> jax.Array:
        """Time of impact τ of ``x + τ p`` (fraction of the step p; +inf if none)."""
        o = self.offset(t)
        return conservative_toi(self.sdf, x - o, p)


def _register(cls, data: list[str], meta: list[str] = ["motion"]):  # noqa: B006
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    return cls


@dataclasses.dataclass(frozen=True)
class HalfSpace(_Moving):
    """The half-space ``(x − point)·n ≤ 0`` (the ground: normal pointing into the free side).

    Attributes:
        point: ``(dim,)`` a point of the plane [m]; normal: ``(dim,)`` outward normal (any
            length; normalised); friction: Coulomb coefficient μ ``()``; motion: optional
            ``t -> (dim,)`` translation [m] (static).
    """

    point: jax.Array
    normal: jax.Array
    friction: Any = 0.0
    motion: Callable | None = None

    def _ref(self):
        return jnp.asarray(self.point)

    def _n(self):
        n = jnp.asarray(self.normal, self._ref().dtype)
        return n / jnp.sqrt(jnp.sum(n * n))

    def sdf(self, x):
        return jnp.sum((x - self.point) * self._n())

    def toi(self, x, p, t=0.0):
        n = self._n()
        d0 = self.distance(x, t)
        v = jnp.sum(p * n)  # < 0: approaching
        approaching = v < 0
        return jnp.where(
            approaching, jnp.maximum(d0, 0.0) / jnp.where(approaching, -v, 1.0), jnp.inf
        )


@dataclasses.dataclass(frozen=True)
class Sphere(_Moving):
    """A ball (a disc in 2D) of ``radius`` [m] around ``center`` ``(dim,)`` [m]."""

    center: jax.Array
    radius: Any
    friction: Any = 0.0
    motion: Callable | None = None

    def _ref(self):
        return jnp.asarray(self.center)

    def sdf(self, x):
        return safe_norm(x - self.center) - self.radius

    def toi(self, x, p, t=0.0):
        q = x - self.center - self.offset(t)
        pp, qp = jnp.sum(p * p), jnp.sum(q * p)
        c = jnp.sum(q * q) - self.radius**2
        disc = qp * qp - pp * c
        hit = (disc >= 0) & (qp < 0) & (pp > 0)
        root = (-qp - jnp.sqrt(jnp.where(hit, disc, 0.0))) / jnp.where(hit, pp, 1.0)
        return jnp.where(hit, jnp.maximum(root, 0.0), jnp.inf)


def _box_sdf(q: jax.Array, half: jax.Array) -> jax.Array:
    """Signed distance of ``q`` (box frame, centred) to a box of half-widths ``half``."""
    e = jnp.abs(q) - half
    return safe_norm(jnp.maximum(e, 0.0)) + jnp.minimum(jnp.max(e), 0.0)


def _slab_toi(q: jax.Array, p: jax.Array, half: jax.Array) -> jax.Array:
    """Entry time of the ray ``q + τp`` into the centred box ``|q| ≤ half`` (slab method)."""
    moving = p != 0
    ps = jnp.where(moving, p, 1.0)
    t1 = jnp.where(moving, (-half - q) / ps, -jnp.inf)
    t2 = jnp.where(moving, (half - q) / ps, jnp.inf)
    inside_slab = jnp.abs(q) <= half
    lo = jnp.where(moving, jnp.minimum(t1, t2), jnp.where(inside_slab, -jnp.inf, jnp.inf))
    hi = jnp.where(moving, jnp.maximum(t1, t2), jnp.where(inside_slab, jnp.inf, -jnp.inf))
    t_in, t_out = jnp.max(lo), jnp.min(hi)
    hit = (t_out >= jnp.maximum(t_in, 0.0)) & jnp.isfinite(t_in)
    return jnp.where(hit, jnp.maximum(t_in, 0.0), jnp.inf)


@dataclasses.dataclass(frozen=True)
class Box(_Moving):
    """The axis-aligned box ``lo ≤ x ≤ hi`` (``(dim,)`` corners [m])."""

    lo: jax.Array
    hi: jax.Array
    friction: Any = 0.0
    motion: Callable | None = None

    def _ref(self):
        return jnp.asarray(self.lo)

    def sdf(self, x):
        return _box_sdf(x - 0.5 * (self.lo + self.hi), 0.5 * (self.hi - self.lo))

    def toi(self, x, p, t=0.0):
        q = x - self.offset(t) - 0.5 * (self.lo + self.hi)
        return _slab_toi(q, p, 0.5 * (self.hi - self.lo))


@dataclasses.dataclass(frozen=True)
class RotatedBox(_Moving):
    """A box of half-widths ``half`` ``(dim,)`` [m] around ``center``, with its axes the
    columns of the rotation ``rotation`` ``(dim, dim)`` (box frame → world)."""

    center: jax.Array
    half: jax.Array
    rotation: jax.Array
    friction: Any = 0.0
    motion: Callable | None = None

    def _ref(self):
        return jnp.asarray(self.center)

    def sdf(self, x):
        return _box_sdf(self.rotation.T @ (x - self.center), self.half)

    def toi(self, x, p, t=0.0):
        q = self.rotation.T @ (x - self.offset(t) - self.center)
        return _slab_toi(q, self.rotation.T @ p, self.half)


@dataclasses.dataclass(frozen=True)
class Capsule(_Moving):
    """Points within ``radius`` [m] of the segment ``a``–``b`` (``(dim,)`` [m])."""

    a: jax.Array
    b: jax.Array
    radius: Any
    friction: Any = 0.0
    motion: Callable | None = None

    def _ref(self):
        return jnp.asarray(self.a)

    def sdf(self, x):
        ab = self.b - self.a
        s = jnp.clip(jnp.sum((x - self.a) * ab) / jnp.sum(ab * ab), 0.0, 1.0)
        return safe_norm(x - self.a - s * ab) - self.radius


@dataclasses.dataclass(frozen=True)
class SDF(_Moving):
    """A user signed-distance function ``fn(x, params) -> d`` written in JAX.

    ``fn`` must be a Euclidean signed distance (‖∇d‖ ≤ 1, positive outside) for the
    conservative CCD to be safe, and twice differentiable where contact happens (the
    barrier's Hessian uses its second derivatives).

    Attributes:
        fn: static callable ``(x (dim,), params) -> ()`` [m]; params: pytree of its
            parameters (leaves: differentiable); dim: the point dimension (2 or 3).
    """

    fn: Callable
    params: Any
    dim: int = 3
    friction: Any = 0.0
    motion: Callable | None = None

    def _ref(self):
        leaves = [a for a in jax.tree_util.tree_leaves(self.params) if hasattr(a, "dtype")]
        dt = leaves[0].dtype if leaves else jnp.zeros(()).dtype
        return jnp.zeros((self.dim,), dt)

    def sdf(self, x):
        return self.fn(x, self.params)


_register(HalfSpace, ["point", "normal", "friction"])
_register(Sphere, ["center", "radius", "friction"])
_register(Box, ["lo", "hi", "friction"])
_register(RotatedBox, ["center", "half", "rotation", "friction"])
_register(Capsule, ["a", "b", "radius", "friction"])
_register(SDF, ["params", "friction"], ["fn", "dim", "motion"])

Obstacle = HalfSpace | Sphere | Box | RotatedBox | Capsule | SDF


NORMAL_LENGTHS = (1e-100, 1e100)
"""The lengths of a half-space normal :func:`check_obstacle` accepts (its square must
neither underflow nor overflow in float64)."""


def _concrete(v) -> np.ndarray | None:
    """NumPy value of a leaf, or None when it is traced (checked only when concrete)."""
    try:
        return np.asarray(v, dtype=np.float64)
    except Exception:  # noqa: BLE001 — a tracer (inside jit/grad)
        return None


def check_obstacle(ob, name: str = "obstacle") -> None:
    """Refuse an obstacle no solve can use, naming the field: a negative or non-finite
    friction coefficient, a zero or non-finite half-space normal, a sphere or capsule
    radius ≤ 0, a box with ``hi ≤ lo`` or half-widths ≤ 0, a rotation that is not
    orthonormal, non-finite coordinates. Traced fields are not checked. Used by
    :func:`~jaxelastic.contact.make_contact` (the Python API and the scenes alike).

    Raises:
        TypeError: not an obstacle; ValueError: naming ``name`` and the field.
    """
    types = (HalfSpace, Sphere, Box, RotatedBox, Capsule, SDF)
    if not isinstance(ob, types):
        raise TypeError(
            f"{name}: an obstacle must be one of HalfSpace, Sphere, Box, RotatedBox, "
            f"Capsule, SDF (jaxelastic.contact), got {type(ob).__name__}"
        )
    kind = type(ob).__name__
    fields = [f.name for f in dataclasses.fields(ob) if f.name not in ("fn", "motion", "dim")]
    for f in fields:
        if f == "params":
            continue
        a = _concrete(getattr(ob, f))
        if a is not None and not np.all(np.isfinite(a)):
            raise ValueError(f"{name} ({kind}): {f} must be finite, got {a.tolist()}")
    mu = _concrete(ob.friction)
    if mu is not None and np.any(mu < 0):
        raise ValueError(
            f"{name} ({kind}): friction (the Coulomb coefficient mu) must be >= 0, got "
            f"{mu.tolist()}"
        )
    if isinstance(ob, HalfSpace):
        n = _concrete(ob.normal)
        length = None if n is None else float(np.sqrt(np.sum(n * n)))
        if (
            n is not None
            and length is not None
            and not (NORMAL_LENGTHS[0] <= length <= NORMAL_LENGTHS[1])
        ):
            raise ValueError(
                f"{name} ({kind}): normal must be a non-zero vector pointing into the free "
                f"side, of length between {NORMAL_LENGTHS[0]:g} and {NORMAL_LENGTHS[1]:g} "
                f"(it is normalised; a unit vector is best), got {n.tolist()}"
            )
    if isinstance(ob, (Sphere, Capsule)):
        r = _concrete(ob.radius)
        if r is not None and np.any(r <= 0):
            raise ValueError(f"{name} ({kind}): radius must be > 0, got {r.tolist()}")
    if isinstance(ob, Box):
        lo, hi = _concrete(ob.lo), _concrete(ob.hi)
        if lo is not None and hi is not None and np.any(hi <= lo):
            raise ValueError(
                f"{name} ({kind}): hi must exceed lo in every coordinate, got lo = "
                f"{lo.tolist()}, hi = {hi.tolist()}"
            )
    if isinstance(ob, RotatedBox):
        half, R = _concrete(ob.half), _concrete(ob.rotation)
        if half is not None and np.any(half <= 0):
            raise ValueError(f"{name} ({kind}): half-widths must be > 0, got {half.tolist()}")
        if R is not None and not np.allclose(R.T @ R, np.eye(len(R)), atol=1e-8):
            raise ValueError(f"{name} ({kind}): rotation must be orthonormal (R^T R = I)")


def interior_point(ob) -> jax.Array | None:
    """A point inside the obstacle at rest ``(dim,)`` [m] (None for a user SDF, whose
    inside is unknown): the centre of a sphere or box, the midpoint of a capsule's axis,
    a point one unit behind a half-space's plane."""
    if isinstance(ob, HalfSpace):
        return jnp.asarray(ob.point) - ob._n()
    if isinstance(ob, Sphere):
        return jnp.asarray(ob.center)
    if isinstance(ob, Box):
        return 0.5 * (jnp.asarray(ob.lo) + jnp.asarray(ob.hi))
    if isinstance(ob, RotatedBox):
        return jnp.asarray(ob.center)
    if isinstance(ob, Capsule):
        return 0.5 * (jnp.asarray(ob.a) + jnp.asarray(ob.b))
    return None
