"""Scene ``[[obstacle]]`` / ``[contact]`` tables → a contact term, and its summary entries.

A scene without ``[[obstacle]]`` and without ``[contact] self = true`` gets no contact term
(``Potential.contact = None``).
"""

from __future__ import annotations

import functools
import re
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..contact import Box, HalfSpace, Sphere, make_contact
from ..mechanics.potential import Potential
from .callables import CallableSpecError, import_callable
from .load import Scene
from .schema import ContactSpec

__all__ = ["build_contact", "contact_report", "min_gap"]


def _obstacle(scene: Scene, i: int, spec, mu: float, dtype):
    key = f"[[obstacle]][{i}]"
    motion = None
    if spec.motion is not None:
        try:
            motion = import_callable(spec.motion, scene.base_dir)
        except CallableSpecError as e:
            raise scene.error(f"{key}.motion: {e}") from None
    a = functools.partial(jnp.asarray, dtype=dtype)
    f = a(mu)
    if spec.plane is not None:
        if not np.any(np.asarray(spec.plane.normal)):
            raise scene.error(f"{key}.plane.normal must not be zero")
        return HalfSpace(a(spec.plane.point), a(spec.plane.normal), f, motion)
    if spec.sphere is not None:
        return Sphere(a(spec.sphere.center), a(spec.sphere.radius), f, motion)
    return Box(a(spec.box.lo), a(spec.box.hi), f, motion)


def build_contact(scene: Scene, pot: Potential) -> Potential:
    """``pot`` with the scene's contact term (unchanged without ``[[obstacle]]`` and
    self-contact).

    Raises:
        SceneError: ``[contact]`` without obstacles nor ``self = true``, ``self_friction``
            without ``self = true``, a body node inside an obstacle at the rest shape, or
            the boundary touching itself at rest.
    """
    spec = scene.spec
    self_contact = spec.contact is not None and spec.contact.self_contact
    if not spec.obstacle and not self_contact:
        if spec.contact is not None:
            raise scene.error("[contact] needs at least one [[obstacle]] or self = true")
        return pot
    cs = spec.contact or ContactSpec()
    if cs.self_friction > 0 and not self_contact:
        raise scene.error("[contact].self_friction needs self = true")
    dt = pot.mesh.points.dtype
    obs = [
        _obstacle(scene, i, o, cs.friction if o.friction is None else o.friction, dt)
        for i, o in enumerate(spec.obstacle)
    ]
    try:
        c = make_contact(
            pot,
            obs,
            dhat=cs.dhat,
            kappa=cs.kappa,
            self_contact=self_contact,
            margin=cs.margin,
            self_friction=cs.self_friction if cs.self_friction > 0 else None,
        )
    except ValueError as e:
        raise scene.error(_contact_key(str(e), bool(obs))) from None
    return pot.replace(contact=c)


def _contact_key(msg: str, obstacles: bool) -> str:
    """A :func:`~jaxelastic.contact.make_contact` error with the scene key it is about:
    ``obstacle 1 (Sphere) …`` → ``[[obstacle]][1] (Sphere) …``, ``dhat …`` →
    ``[contact].dhat …``."""
    m = re.match(r"obstacle (\d+) ", msg)
    if m:
        return f"[[obstacle]][{m.group(1)}] " + msg[m.end() :]
    if msg.startswith(("dhat", "kappa")):
        return f"[contact].{msg}"
    return f"{'[[obstacle]]' if obstacles else '[contact]'}: {msg}"


@jax.jit
def _gap_and_force(contact, x, t):
    c = contact.at_time(t)
    f = c.forces(x)  # self-contact forces sum to zero: the total is the obstacles'
    active = jnp.sum(jnp.any(c.distances(x) < c.dhat, axis=0))
    return c.min_distance(x), jnp.sum(f, axis=0), active


def _fresh(contact, x):
    """The contact with its self-contact broad phase at ``x`` (host; else unchanged)."""
    return contact if contact.self_contact is None else contact.refreshed(np.asarray(x), force=True)


def min_gap(pot: Potential, x, t: Any = 0.0) -> float:
    """Smallest node–obstacle distance [m] at ``x`` ``(n, dim)`` with obstacles at ``t``."""
    return float(_gap_and_force(_fresh(pot.contact, x), x, t)[0])


def contact_report(pot: Potential, x, t: Any = 0.0, min_distance: float | None = None) -> dict:
    """``summary.json`` entries of a contact scene at the final ``x``: ``min_distance``
    over the run (``min_distance``, else at ``x``) [m], ``total_contact_force`` ``(dim,)``
    [N] (barrier + friction, on the body), ``active_nodes`` (within d̂), ``dhat`` [m] and
    ``kappa`` [N/m]."""
    c = _fresh(pot.contact, x)
    d, f, active = _gap_and_force(c, x, t)
    return dict(
        min_distance=float(d) if min_distance is None else min(float(d), min_distance),
        final_min_distance=float(d),
        total_contact_force=np.asarray(f).tolist(),
        active_nodes=int(active),
        dhat=float(c.dhat),
        kappa=float(c.kappa),
    )
