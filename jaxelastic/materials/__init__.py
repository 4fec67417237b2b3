"""Material laws: strain-energy densities ψ(F, params) → scalar and their parameter types.

A material is nothing but a function of one unbatched deformation gradient ``F`` of shape
``(d, d)`` (d = 2 or 3) and a parameter pytree; every derived quantity is obtained by JAX
transformations, so any user function with the same signature works everywhere a built-in
does.

* :mod:`~jaxelastic.materials.parameters`: :class:`Lame`, :func:`lame` (E, ν → μ, λ),
  :func:`check_lame`;
* :mod:`~jaxelastic.materials.isotropic`: linear, StVK, corotated, fixed corotated, ARAP,
  neo-Hookean, stable neo-Hookean, the isochoric neo-Hookean of the JAX-FEM twist;
* :mod:`~jaxelastic.materials.rubber`: Mooney–Rivlin, Yeoh, Ogden, Gent, Arruda–Boyce;
* :mod:`~jaxelastic.materials.fibres`: Holzapfel–Gasser–Ogden with fibre dispersion;
* :mod:`~jaxelastic.materials.cardiac`: Guccione's law of passive myocardium and the
  active fibre tension wrapper;
* :mod:`~jaxelastic.materials.fibre_rules`: the helix fibre rule of an ellipsoidal ventricle;
* :mod:`~jaxelastic.materials.spectral`: spectral functions of ``C`` with finite
  derivatives at repeated stretches (custom JVPs);
* :mod:`~jaxelastic.materials.registry`: the one table of built-in laws and parameter types
  (:data:`BUILTIN`, :data:`FAMILIES`, :data:`FAMILY_PARAMS`) the scene schema reads;
* :mod:`~jaxelastic.materials.reference`: hand-derived P of every built-in, for the
  autodiff cross-checks only.
"""

from . import cardiac as cardiac
from . import fibre_rules as fibre_rules
from . import fibres as fibres
from . import reference as reference
from . import rubber as rubber
from . import spectral as spectral
from .cardiac import ActiveTension as ActiveTension
from .cardiac import Guccione as Guccione
from .cardiac import guccione as guccione
from .cardiac import guccione_params as guccione_params
from .cardiac import per_cell_basis as per_cell_basis
from .cardiac import per_quadrature_basis as per_quadrature_basis
from .cardiac import with_active_tension as with_active_tension
from .fibre_rules import helix_basis as helix_basis
from .fibre_rules import helix_fibres as helix_fibres
from .fibres import HolzapfelGasserOgden as HolzapfelGasserOgden
from .fibres import fibre_pair as fibre_pair
from .fibres import holzapfel_gasser_ogden as holzapfel_gasser_ogden
from .fibres import holzapfel_gasser_ogden_params as holzapfel_gasser_ogden_params
from .fibres import per_cell_fibres as per_cell_fibres
from .isotropic import arap as arap
from .isotropic import corotated as corotated
from .isotropic import fixed_corotated as fixed_corotated
from .isotropic import isochoric_neo_hookean as isochoric_neo_hookean
from .isotropic import linear as linear
from .isotropic import neo_hookean as neo_hookean
from .isotropic import stable_neo_hookean as stable_neo_hookean
from .isotropic import stable_neo_hookean_log as stable_neo_hookean_log
from .isotropic import stvk as stvk
from .parameters import LAME_RATIO_MAX as LAME_RATIO_MAX
from .parameters import Lame as Lame
from .parameters import check_lame as check_lame
from .parameters import lame as lame
from .registry import BUILTIN as BUILTIN
from .registry import DIRECTION_KEYS as DIRECTION_KEYS
from .registry import FAMILIES as FAMILIES
from .registry import FAMILY_KEYS as FAMILY_KEYS
from .registry import FAMILY_PARAMS as FAMILY_PARAMS
from .registry import FAMILY_POSITIVE_KEYS as FAMILY_POSITIVE_KEYS
from .registry import FAMILY_TYPES as FAMILY_TYPES
from .registry import MODEL_NAMES as MODEL_NAMES
from .registry import MaterialParameterError as MaterialParameterError
from .registry import check_family as check_family
from .registry import check_guccione as check_guccione
from .registry import check_material as check_material
from .rubber import ArrudaBoyce as ArrudaBoyce
from .rubber import Gent as Gent
from .rubber import MooneyRivlin as MooneyRivlin
from .rubber import Ogden as Ogden
from .rubber import Yeoh as Yeoh
from .rubber import arruda_boyce as arruda_boyce
from .rubber import arruda_boyce_params as arruda_boyce_params
from .rubber import gent as gent
from .rubber import gent_params as gent_params
from .rubber import mooney_rivlin as mooney_rivlin
from .rubber import mooney_rivlin_params as mooney_rivlin_params
from .rubber import ogden as ogden
from .rubber import ogden_params as ogden_params
from .rubber import yeoh as yeoh
from .rubber import yeoh_params as yeoh_params

__all__ = [
    "cardiac",
    "fibre_rules",
    "fibres",
    "reference",
    "rubber",
    "spectral",
    "HolzapfelGasserOgden",
    "holzapfel_gasser_ogden",
    "holzapfel_gasser_ogden_params",
    "fibre_pair",
    "per_cell_fibres",
    "ActiveTension",
    "Guccione",
    "check_guccione",
    "guccione",
    "guccione_params",
    "per_cell_basis",
    "per_quadrature_basis",
    "with_active_tension",
    "helix_basis",
    "helix_fibres",
    "DIRECTION_KEYS",
    "linear",
    "stvk",
    "corotated",
    "neo_hookean",
    "stable_neo_hookean",
    "stable_neo_hookean_log",
    "fixed_corotated",
    "arap",
    "isochoric_neo_hookean",
    "Lame",
    "lame",
    "check_lame",
    "LAME_RATIO_MAX",
    "BUILTIN",
    "FAMILIES",
    "FAMILY_PARAMS",
    "FAMILY_TYPES",
    "MODEL_NAMES",
    "FAMILY_KEYS",
    "FAMILY_POSITIVE_KEYS",
    "MaterialParameterError",
    "check_family",
    "check_material",
    "MooneyRivlin",
    "mooney_rivlin",
    "mooney_rivlin_params",
    "Yeoh",
    "yeoh",
    "yeoh_params",
    "Ogden",
    "ogden",
    "ogden_params",
    "Gent",
    "gent",
    "gent_params",
    "ArrudaBoyce",
    "arruda_boyce",
    "arruda_boyce_params",
]
