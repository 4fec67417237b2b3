"""Material identification: fit any parameter of any ψ (shared, per region or per cell).

* :mod:`~jaxelastic.fitting.transforms`: ``Positive``, ``Bounded``, ``Free``, ``Fixed``;
* :mod:`~jaxelastic.fitting.parameters`: :class:`Parametrization` of a parameter pytree
  (transforms, spatial layout, regularisation over adjacent regions);
* :mod:`~jaxelastic.fitting.elastic`: the (E, ν) convenience, :class:`Material`;
* :mod:`~jaxelastic.fitting.observations`: misfit, noise, markers, nested meshes;
* :mod:`~jaxelastic.fitting.measurements`: the observation protocol and its kinds
  (:class:`Positions`, :class:`Points`, :class:`Reaction`, :class:`Moment`,
  :class:`CavityVolume`, :class:`Surface`);
* :mod:`~jaxelastic.fitting.cases`: the case protocol, :class:`LoadCase`,
  :class:`TrajectoryCase`, :class:`LoadPathCase` (load levels with observations);
* :mod:`~jaxelastic.fitting.objective`: the compiled objective in unconstrained variables;
* :mod:`~jaxelastic.fitting.optimization`: :func:`fit` with optax;
* :mod:`~jaxelastic.fitting.identifiability`: :func:`loss_landscape`, :func:`loss_hessian`;
* :mod:`~jaxelastic.fitting.uncertainty`: :func:`gauss_newton_uncertainty` at an optimum;
* :mod:`~jaxelastic.fitting.least_squares`: :func:`levenberg_marquardt` for few parameters;
* :mod:`~jaxelastic.fitting.homogeneous`: uniaxial, equibiaxial, pure-shear and simple-shear
  stress of any ψ without a mesh (:func:`nominal_stress`), and :func:`fit_curves` of
  measured test curves (:func:`stress_curve`).
"""

from .cases import Case as Case
from .cases import CaseAux as CaseAux
from .cases import LoadCase as LoadCase
from .cases import LoadPathCase as LoadPathCase
from .cases import TrajectoryCase as TrajectoryCase
from .elastic import LameOf as LameOf
from .elastic import Material as Material
from .elastic import material_parametrization as material_parametrization
from .identifiability import loss_hessian as loss_hessian
from .identifiability import loss_landscape as loss_landscape
from .measurements import CavityVolume as CavityVolume
from .measurements import Moment as Moment
from .measurements import Observation as Observation
from .measurements import Points as Points
from .measurements import Positions as Positions
from .measurements import Reaction as Reaction
from .measurements import SolvedState as SolvedState
from .measurements import Surface as Surface
from .measurements import locate_points as locate_points
from .objective import FIT_SOLVER as FIT_SOLVER
from .objective import Objective as Objective
from .objective import fitted_values as fitted_values
from .objective import make_objective as make_objective
from .objective import parametrize as parametrize
from .observations import add_noise as add_noise
from .observations import choose_markers as choose_markers
from .observations import nested_nodes as nested_nodes
from .observations import observation_loss as observation_loss
from .optimization import FitResult as FitResult
from .optimization import describe_failure as describe_failure
from .optimization import fit as fit
from .parameters import Parametrization as Parametrization
from .parameters import make_parametrization as make_parametrization
from .parameters import region_adjacency as region_adjacency
from .transforms import Bounded as Bounded
from .transforms import Fixed as Fixed
from .transforms import Free as Free
from .transforms import Positive as Positive
from .transforms import Transform as Transform
from .uncertainty import Uncertainty as Uncertainty
from .uncertainty import gauss_newton_uncertainty as gauss_newton_uncertainty

# isort: split
# homogeneous test curves and their least-squares fit
from .homogeneous import TESTS as TESTS
from .homogeneous import CurveFit as CurveFit
from .homogeneous import FreeStretchNewton as FreeStretchNewton
from .homogeneous import HomogeneousResponse as HomogeneousResponse
from .homogeneous import StressCurve as StressCurve
from .homogeneous import fit_curves as fit_curves
from .homogeneous import homogeneous_deformation as homogeneous_deformation
from .homogeneous import nominal_stress as nominal_stress
from .homogeneous import stress_curve as stress_curve
from .least_squares import LeastSquaresResult as LeastSquaresResult
from .least_squares import LMSettings as LMSettings
from .least_squares import levenberg_marquardt as levenberg_marquardt

__all__ = [
    "Case",
    "CaseAux",
    "LoadCase",
    "LoadPathCase",
    "Moment",
    "CavityVolume",
    "Observation",
    "Points",
    "Positions",
    "Reaction",
    "SolvedState",
    "Surface",
    "locate_points",
    "fitted_values",
    "describe_failure",
    "TrajectoryCase",
    "LameOf",
    "Material",
    "material_parametrization",
    "loss_hessian",
    "loss_landscape",
    "FIT_SOLVER",
    "Objective",
    "make_objective",
    "parametrize",
    "add_noise",
    "choose_markers",
    "nested_nodes",
    "observation_loss",
    "FitResult",
    "fit",
    "Parametrization",
    "make_parametrization",
    "region_adjacency",
    "Bounded",
    "Fixed",
    "Free",
    "Positive",
    "Transform",
    "Uncertainty",
    "gauss_newton_uncertainty",
    # homogeneous test curves and their least-squares fit
    "TESTS",
    "CurveFit",
    "FreeStretchNewton",
    "HomogeneousResponse",
    "StressCurve",
    "fit_curves",
    "homogeneous_deformation",
    "nominal_stress",
    "stress_curve",
    "LeastSquaresResult",
    "LMSettings",
    "levenberg_marquardt",
]
