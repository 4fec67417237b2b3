"""Barrier contact against rigid obstacles (IPC: Li et al. 2020, "Incremental Potential
Contact", ACM TOG 39(4)), as one more term of the potential Newton minimises.

* :mod:`~jaxelastic.contact.obstacles`: half-space, sphere, boxes, capsule, user SDF;
* :mod:`~jaxelastic.contact.barrier`: the clamped log barrier, d̂ and κ;
* :mod:`~jaxelastic.contact.friction`: lagged smoothed Coulomb friction;
* :mod:`~jaxelastic.contact.ccd`: the intersection-free line-search bound;
* :mod:`~jaxelastic.contact.term`: the :class:`Contact` term held by ``Potential.contact``;
* :mod:`~jaxelastic.contact.setup`: :func:`make_contact` (automatic d̂, κ), :func:`adapt`.

Self-contact (point–triangle, edge–edge, broad phase) is not implemented yet.
"""

from .barrier import barrier as barrier
from .barrier import barrier_d1 as barrier_d1
from .barrier import barrier_d2 as barrier_d2
from .ccd import ccd_step as ccd_step
from .friction import FrictionLag as FrictionLag
from .obstacles import SDF as SDF
from .obstacles import Box as Box
from .obstacles import Capsule as Capsule
from .obstacles import HalfSpace as HalfSpace
from .obstacles import Obstacle as Obstacle
from .obstacles import RotatedBox as RotatedBox
from .obstacles import Sphere as Sphere
from .setup import adapt as adapt
from .setup import auto_kappa as auto_kappa
from .setup import contact_nodes as contact_nodes
from .setup import make_contact as make_contact
from .setup import with_contact as with_contact
from .term import Contact as Contact

__all__ = [
    "barrier",
    "barrier_d1",
    "barrier_d2",
    "ccd_step",
    "FrictionLag",
    "SDF",
    "Box",
    "Capsule",
    "HalfSpace",
    "Obstacle",
    "RotatedBox",
    "Sphere",
    "adapt",
    "auto_kappa",
    "contact_nodes",
    "make_contact",
    "with_contact",
    "Contact",
]
