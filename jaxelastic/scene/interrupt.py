"""Interruptions of a run: SIGINT/SIGTERM stop at the next step boundary.

:func:`handle_signals` (the CLI wraps ``run`` and ``fit`` in it) installs handlers for
SIGINT and SIGTERM that only *record* the first signal: the run polls :func:`requested` at
its step boundaries (after a time step, a load increment, a build or target solve), stops
there, writes consistent outputs (a ``.pvd`` listing only the files written, a
``summary.json`` with ``"interrupted": true``) and raises :class:`Interrupted`. A second
signal, and the first one inside :func:`immediate` (a phase without step boundaries of its
own, e.g. the optimiser of a fit), raises :class:`Interrupted` at once, except inside
:func:`shield` (writing the final outputs of a stopped run). Without the
handlers (a plain Python session) Ctrl-C raises ``KeyboardInterrupt`` as usual, which the
run treats the same way.

:class:`Interrupted` subclasses ``KeyboardInterrupt``, so ``except Exception`` clauses do
not swallow it and :func:`jaxelastic.io.write_atomic` removes its temporary file.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

__all__ = [
    "Interrupted",
    "handle_signals",
    "requested",
    "check",
    "immediate",
    "shield",
    "signal_name",
]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A run stopped by SIGINT/SIGTERM (or Ctrl-C).

    Attributes:
        signame: ``"SIGINT"``, ``"SIGTERM"`` (or ``"KeyboardInterrupt"``).
        detail: what was completed, e.g. ``"after 12 of 500 time steps (t = 0.12 s)"``.
        out: the output directory holding the partial results, or None.
    """

    def __init__(self, signame: str = "SIGINT", detail: str = "", out: str | None = None):
        super().__init__(signame)
        self.signame, self.detail, self.out = signame, detail, out


class _State:
    installed = False
    signame: str | None = None  # the first signal received
    raise_now = False  # inside immediate()
    shielded = 0  # depth of shield() blocks


_state = _State()


def signal_name(signum: int) -> str:
    """``"SIGINT"``, ``"SIGTERM"``, … for a signal number."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def _handler(signum, frame) -> None:
    name = signal_name(signum)
    first = _state.signame is None
    if first:
        _state.signame = name
    if (not first or _state.raise_now) and not _state.shielded:
        raise Interrupted(name)


@contextlib.contextmanager
def handle_signals() -> Iterator[None]:
    """Record SIGINT/SIGTERM instead of raising (main thread only; elsewhere a no-op);
    the previous handlers are restored on exit."""
    if threading.current_thread() is not threading.main_thread() or _state.installed:
        yield
        return
    previous = {s: signal.getsignal(s) for s in _SIGNALS}
    _state.installed, _state.signame, _state.raise_now = True, None, False
    try:
        for s in _SIGNALS:
            signal.signal(s, _handler)
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _state.installed, _state.signame, _state.raise_now = False, None, False


def requested() -> str | None:
    """The name of the signal received (a stop is requested), or None."""
    return _state.signame


def check(detail: str = "") -> None:
    """Raise :class:`Interrupted` if a stop was requested (call at a step boundary)."""
    if _state.signame is not None:
        raise Interrupted(_state.signame, detail)


@contextlib.contextmanager
def immediate() -> Iterator[None]:
    """Inside this block a signal raises :class:`Interrupted` at once (for phases with no
    step boundary the run can poll); a signal already received raises on entry."""
    check()
    old, _state.raise_now = _state.raise_now, True
    try:
        yield
    finally:
        _state.raise_now = old


def at_boundaries() -> None:
    """From now on (until the enclosing :func:`immediate` block ends) a first signal is
    only recorded again: for a phase that has just reached its first step boundary, e.g.
    an optimiser past its compilation whose iterations can now be polled."""
    _state.raise_now = False


@contextlib.contextmanager
def shield() -> Iterator[None]:
    """Inside this block signals are only recorded, never raised (writing the outputs of a
    stopped run: they are short, and must not be cut in half)."""
    _state.shielded += 1
    try:
        yield
    finally:
        _state.shielded -= 1
