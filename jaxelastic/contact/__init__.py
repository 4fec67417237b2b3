"""Barrier contact against rigid obstacles (IPC: Li et al. 2020, "Incremental Potential
Contact", ACM TOG 39(4)), as one more term of the potential Newton minimises.

* :mod:`~jaxelastic.contact.obstacles`: half-space, sphere, boxes, capsule, user SDF;
* :mod:`~jaxelastic.contact.log_barrier`: the clamped log barrier, d̂ and κ;
* :mod:`~jaxelastic.contact.friction`: lagged smoothed Coulomb friction;
* :mod:`~jaxelastic.contact.ccd`: the intersection-free line-search bound;
* :mod:`~jaxelastic.contact.term`: the :class:`Contact` term held by ``Potential.contact``;
* :mod:`~jaxelastic.contact.setup`: :func:`make_contact` (automatic d̂, κ), :func:`adapt`;
* self-contact: :mod:`~jaxelastic.contact.distance` (point–triangle, edge–edge with the
  parallel-edge mollifier, 2D point–edge), :mod:`~jaxelastic.contact.broadphase` (host
  spatial hash), :mod:`~jaxelastic.contact.pairs` (:class:`SelfContact`, the pair barrier),
  :mod:`~jaxelastic.contact.pair_friction` (lagged friction of the pairs) and additive
  CCD (:func:`~jaxelastic.contact.ccd.additive_toi`).
"""

from .broadphase import Surface as Surface
from .broadphase import candidate_pairs as candidate_pairs
from .broadphase import surface_of as surface_of
from .ccd import additive_toi as additive_toi
from .ccd import ccd_step as ccd_step
from .friction import FrictionLag as FrictionLag
from .log_barrier import barrier as barrier
from .log_barrier import barrier_d1 as barrier_d1
from .log_barrier import barrier_d2 as barrier_d2
from .obstacles import SDF as SDF
from .obstacles import Box as Box
from .obstacles import Capsule as Capsule
from .obstacles import HalfSpace as HalfSpace
from .obstacles import Obstacle as Obstacle
from .obstacles import RotatedBox as RotatedBox
from .obstacles import Sphere as Sphere
from .pair_friction import PairFrictionLag as PairFrictionLag
from .pairs import SelfContact as SelfContact
from .pairs import make_self_contact as make_self_contact
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
    "Surface",
    "candidate_pairs",
    "surface_of",
    "additive_toi",
    "ccd_step",
    "FrictionLag",
    "SDF",
    "Box",
    "Capsule",
    "HalfSpace",
    "Obstacle",
    "RotatedBox",
    "Sphere",
    "PairFrictionLag",
    "SelfContact",
    "make_self_contact",
    "adapt",
    "auto_kappa",
    "contact_nodes",
    "make_contact",
    "with_contact",
    "Contact",
]
