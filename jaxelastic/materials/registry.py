"""The table of built-in material laws, their names and parameter types.

:data:`BUILTIN` maps the name of every law of :class:`~jaxelastic.materials.parameters.Lame`
parameters to its ψ; :data:`FAMILIES` the rubber and soft-tissue laws to theirs, each with
its own parameter type, whose documented typical values :data:`FAMILY_PARAMS` builds.
:data:`MODEL_NAMES`, :data:`FAMILY_KEYS` and :data:`FAMILY_POSITIVE_KEYS` are what the scene
schema validates ``[material]`` against.
"""

from __future__ import annotations

from .cardiac import Guccione, guccione, guccione_params
from .fibres import HolzapfelGasserOgden, holzapfel_gasser_ogden, holzapfel_gasser_ogden_params
from .isotropic import (
    arap,
    corotated,
    fixed_corotated,
    linear,
    neo_hookean,
    stable_neo_hookean,
    stable_neo_hookean_log,
    stvk,
)
from .rubber import (
    ArrudaBoyce,
    Gent,
    MooneyRivlin,
    Ogden,
    Yeoh,
    arruda_boyce,
    arruda_boyce_params,
    gent,
    gent_params,
    mooney_rivlin,
    mooney_rivlin_params,
    ogden,
    ogden_params,
    yeoh,
    yeoh_params,
)

__all__ = [
    "BUILTIN",
    "FAMILIES",
    "FAMILY_PARAMS",
    "FAMILY_TYPES",
    "MODEL_NAMES",
    "FAMILY_KEYS",
    "FAMILY_POSITIVE_KEYS",
    "DIRECTION_KEYS",
]

BUILTIN = {
    "linear": linear,
    "stvk": stvk,
    "corotated": corotated,
    "neo_hookean": neo_hookean,
    "stable_neo_hookean": stable_neo_hookean,
    "stable_neo_hookean_log": stable_neo_hookean_log,
    "fixed_corotated": fixed_corotated,
    "arap": arap,
}
"""Name → ψ of every built-in model (a read-only mapping by convention)."""


FAMILIES = {
    "mooney_rivlin": mooney_rivlin,
    "yeoh": yeoh,
    "ogden": ogden,
    "gent": gent,
    "arruda_boyce": arruda_boyce,
    "holzapfel_gasser_ogden": holzapfel_gasser_ogden,
    "guccione": guccione,
}
"""Name → ψ of the rubber and soft-tissue models (:mod:`jaxelastic.materials.rubber`,
:mod:`jaxelastic.materials.fibres`), each with its own parameter type (not
:class:`~jaxelastic.materials.parameters.Lame`)."""

FAMILY_PARAMS = {
    "mooney_rivlin": mooney_rivlin_params,
    "yeoh": yeoh_params,
    "ogden": ogden_params,
    "gent": gent_params,
    "arruda_boyce": arruda_boyce_params,
    "holzapfel_gasser_ogden": holzapfel_gasser_ogden_params,
    "guccione": guccione_params,
}
"""Name → ``<name>_params(**overrides)``, the documented typical parameters of each of
:data:`FAMILIES` (their types expose ``shear_modulus`` and ``bulk_modulus``)."""


MODEL_NAMES = (*BUILTIN, *FAMILIES)
"""Every built-in model name: the Lamé laws, then the rubber/tissue families."""

FAMILY_TYPES = {
    "mooney_rivlin": MooneyRivlin,
    "yeoh": Yeoh,
    "ogden": Ogden,
    "gent": Gent,
    "arruda_boyce": ArrudaBoyce,
    "holzapfel_gasser_ogden": HolzapfelGasserOgden,
    "guccione": Guccione,
}
"""Name → the parameter type (a ``NamedTuple``) of each of :data:`FAMILIES`."""

# read from the types, not from instances: building the typical values runs JAX, and a
# library import must not start JAX's runtime (jax.distributed.initialize must come first)
FAMILY_KEYS = {name: tuple(t._fields) for name, t in FAMILY_TYPES.items()}
"""Rubber/tissue model name → its parameter keys (the fields of its parameter type, e.g.
``("c10", "c01", "kappa")`` for ``mooney_rivlin``), all required in a scene's ``[material]``."""

FAMILY_POSITIVE_KEYS = frozenset({"c10", "kappa", "Jm", "lambda_m", "k2", "bulk", "mu"}) | {
    "C",  # Guccione (jaxelastic.materials.cardiac.check_guccione)
    "bf",
    "bt",
    "bfs",
}
"""The rubber/tissue parameter keys whose values must be > 0."""

DIRECTION_KEYS = ("a01", "a02", "f0", "s0")
"""The parameter keys that are reference directions (vectors, shared or per cell), not
scalars: HGO's fibres, Guccione's fibre and sheet."""
