"""Per-parameter transforms between a physical value and an unconstrained variable ``z``.

The optimiser of :func:`~jaxelastic.fitting.fit` works on ``z ∈ ℝ``; each fitted leaf of a
material-parameter pytree is ``value = forward(z, ref)``:

* :class:`Positive`: ``value = ref·exp(z)`` (> 0; a step in z is a relative change, the
  same at any scale; ``ref`` is the initial value unless a fixed ``scale`` is given, so
  ``z = 0`` at the start);
* :class:`Bounded`: ``value = lo + (hi − lo)·sigmoid(z)`` (in the open interval);
* :class:`Free`: ``value = z`` or ``scale·z`` (unconstrained);
* :class:`Fixed`: not fitted, held at its initial value.

Transforms are frozen and hashable (static under jit).
"""

from __future__ import annotations

import abc
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Transform", "Positive", "Bounded", "Free", "Fixed"]


class Transform(abc.ABC):
    """Abstract map ``z ↦ value`` of one parameter leaf (element-wise on arrays)."""

    fitted: bool = True
    """False for :class:`Fixed` (the leaf gets no unconstrained variables)."""

    log_scale: bool = False
    """True when the natural coordinate of identifiability studies is ``ln value``."""

    @abc.abstractmethod
    def forward(self, z, ref):
        """Physical value of the unconstrained ``z`` (same shape); ``ref`` from
        :meth:`reference`."""

    @abc.abstractmethod
    def inverse(self, value, ref):
        """Unconstrained ``z`` of a physical ``value`` (same shape)."""

    def reference(self, init):
        """Reference array stored with the parametrisation (default: zeros like init)."""
        return jnp.zeros_like(init)

    def check(self, value, name: str) -> None:
        """Raise ValueError if the (concrete) initial ``value`` is not admissible."""
        if not np.all(np.isfinite(np.asarray(value))):
            raise ValueError(f"parameter {name}: initial value must be finite, got {value!r}")


@dataclasses.dataclass(frozen=True)
class Positive(Transform):
    """``value = ref·exp(z) > 0``, with ``ref = scale`` or (default) the initial value.

    Attributes:
        scale: fixed reference value (same units as the parameter), or None for the
            initial value (then ``z = 0`` at the initial guess).
    """

    scale: float | None = None
    log_scale = True

    def forward(self, z, ref):
        return ref * jnp.exp(z)

    def inverse(self, value, ref):
        return jnp.log(value / ref)

    def reference(self, init):
        if self.scale is None:
            return jnp.asarray(init)
        return jnp.full_like(init, float(self.scale))

    def check(self, value, name: str) -> None:
        super().check(value, name)
        if np.any(np.asarray(value) <= 0):
            raise ValueError(
                f"parameter {name}: Positive() needs an initial value > 0, got {value!r} "
                "(use Free() or Bounded(lo, hi) for parameters that may be ≤ 0)"
            )
        if self.scale is not None and not float(self.scale) > 0:
            raise ValueError(f"parameter {name}: Positive(scale) must be > 0, got {self.scale}")


@dataclasses.dataclass(frozen=True)
class Bounded(Transform):
    """``value = lo + (hi − lo)·sigmoid(z)``, in the open interval ``(lo, hi)``.

    Attributes:
        lo, hi: bounds (``lo < hi``), in the parameter's units.
    """

    lo: float
    hi: float

    def __post_init__(self):
        if not float(self.lo) < float(self.hi):
            raise ValueError(f"Bounded needs lo < hi, got ({self.lo}, {self.hi})")

    def forward(self, z, ref):
        return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(z)

    def inverse(self, value, ref):
        s = (jnp.asarray(value) - self.lo) / (self.hi - self.lo)
        return jnp.log(s) - jnp.log1p(-s)

    def check(self, value, name: str) -> None:
        super().check(value, name)
        v = np.asarray(value)
        if np.any(v <= self.lo) or np.any(v >= self.hi):
            raise ValueError(
                f"parameter {name}: initial value must lie in ({self.lo}, {self.hi}), got {value!r}"
            )


@dataclasses.dataclass(frozen=True)
class Free(Transform):
    """Unconstrained: ``value = z``, or ``value = scale·z`` with a ``scale`` (the
    parameter's typical magnitude, in its units, so that z is of order one).

    Attributes:
        scale: None (identity) or a positive float.
    """

    scale: float | None = None

    def forward(self, z, ref):
        return z if self.scale is None else self.scale * z

    def inverse(self, value, ref):
        v = jnp.asarray(value)
        return v if self.scale is None else v / self.scale

    def check(self, value, name: str) -> None:
        super().check(value, name)
        if self.scale is not None and not float(self.scale) > 0:
            raise ValueError(f"parameter {name}: Free(scale) must be > 0, got {self.scale}")


@dataclasses.dataclass(frozen=True)
class Fixed(Transform):
    """Not fitted: the leaf keeps its initial value."""

    fitted = False

    def forward(self, z, ref):
        raise TypeError("Fixed parameters have no unconstrained variables")

    def inverse(self, value, ref):
        raise TypeError("Fixed parameters have no unconstrained variables")

    def check(self, value, name: str) -> None:
        return None
