"""Mechanics of a strain-energy density ψ: kinematics, energy kernels, element Hessians, the
PSD projection, and the potential the solvers minimise.

* :mod:`~jaxelastic.mechanics.kinematics`: ``F = Ds·Dm⁻¹``, strains, ``det``/``cofactor``,
  the rotation-variant ``polar``, ``svd_rv``, F-bar and B-bar;
* :mod:`~jaxelastic.mechanics.checks`: the input checks of every ``(psi, x, mesh, params)``
  function and the per-cell parameter axes;
* :mod:`~jaxelastic.mechanics.quadrature_fields`: material data per quadrature point
  (:class:`AtQuadrature`);
* :mod:`~jaxelastic.mechanics.kernels`: energy, first Piola stress, forces, HVPs, element
  forces and the scatter-free assembly;
* :mod:`~jaxelastic.mechanics.hessians`: element Hessians by contraction (and the autodiff
  reference);
* :mod:`~jaxelastic.mechanics.psd`: positive-semidefinite projection of Hessians;
* :mod:`~jaxelastic.mechanics.fusion`: XLA fusion control for stored intermediates;
* :mod:`~jaxelastic.mechanics.potential`: :class:`Potential`, elastic energy + loads +
  inertia + damping + contact.
"""

from . import fusion as fusion
from . import kinematics as kinematics
from . import potential as potential
from . import quadrature_fields as quadrature_fields
from .checks import cell_params_axes as cell_params_axes
from .checks import check_finite as check_finite
from .checks import check_positions as check_positions
from .checks import check_psi as check_psi
from .checks import psi_name as psi_name
from .hessians import element_hessians as element_hessians
from .hessians import element_hessians_reference as element_hessians_reference
from .kernels import assemble as assemble
from .kernels import element_forces as element_forces
from .kernels import element_gradient_kernel as element_gradient_kernel
from .kernels import element_gradients as element_gradients
from .kernels import energy as energy
from .kernels import energy_densities as energy_densities
from .kernels import first_piola as first_piola
from .kernels import forces as forces
from .kernels import hvp as hvp
from .potential import Potential as Potential
from .psd import project_element_psd as project_element_psd
from .psd import project_psd as project_psd
from .psd import project_psd_serial as project_psd_serial
from .quadrature_fields import AtQuadrature as AtQuadrature

__all__ = [
    "fusion",
    "kinematics",
    "potential",
    "quadrature_fields",
    "cell_params_axes",
    "check_finite",
    "check_positions",
    "check_psi",
    "psi_name",
    "element_hessians",
    "element_hessians_reference",
    "assemble",
    "element_forces",
    "element_gradients",
    "element_gradient_kernel",
    "energy",
    "energy_densities",
    "first_piola",
    "forces",
    "hvp",
    "Potential",
    "project_element_psd",
    "project_psd",
    "project_psd_serial",
    "AtQuadrature",
]
