"""Command line: ``jaxelastic run [SCENE] --out DIR``, ``jaxelastic fit SCENE --out DIR``,
``jaxelastic crosscheck``, ``jaxelastic scenes``, ``jaxelastic schema`` (also
``python -m jaxelastic ...``).

``run`` without a SCENE runs the shipped ``default`` scene (a neo-Hookean beam released
under gravity, simulated until it settles and compared with the static solution). SCENE is
a TOML file or the name of a shipped scene (``jaxelastic scenes`` lists them);
``--set KEY=VALUE`` overrides a scene entry (VALUE in TOML syntax, e.g.
``--set mesh.n=[10,2,2] --set integrator.duration=1.0``). ``schema`` prints the JSON
Schema of a scene file (``jaxelastic schema > scene.schema.json``) for editors with TOML
schema support (taplo / Even Better TOML); the reference is ``docs/scenes.md``.

After ``run`` and ``fit`` a short table on stdout says what was solved and what came out
(mesh, material, solver, iterations, largest displacement, reaction vs applied load,
energy, time split into compile and run, the files written; see
``docs/guide/outputs.md``); with ``--json`` stdout is one JSON line instead (``status``,
``out``, ``summary``, ``wall_time``, ``compile_time``; ``E`` and ``nu`` of a fit), for
scripts. Progress goes to stderr (``--no-progress`` silences it).

The CLI enables float64 and JAX's persistent compilation cache
(:mod:`jaxelastic.cache`: ``$JAXELASTIC_CACHE_DIR``, default
``$XDG_CACHE_HOME/jaxelastic/jax`` or ``~/.cache/jaxelastic/jax``, at most
``$JAXELASTIC_CACHE_MAX_MB``; ``--no-cache`` turns it off), which cuts the compile time of
a repeated run. (The library enables the same cache lazily at its first solve.)

Exit status: 0 success, 1 a solve failed (the summary is still written), 2 bad usage or
an invalid scene (a mesh too large for the memory included), 130 interrupted.

SIGINT (Ctrl-C) and SIGTERM during ``run`` and ``fit`` stop the run at the next time step
or load increment (the optimiser of a fit: at once): the VTU of the last completed state, a
``.pvd`` listing only the files written and ``summary.json`` with ``"interrupted": true``
are written, temporaries removed, and one line says what was completed (exit status 130).
A second signal stops at once, with the same outputs. Every file is written atomically, so
even SIGKILL leaves only complete files.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import json
import os
import signal
import sys
import threading
import time
import warnings
from typing import NoReturn

from .cache import cache_dir as cache_dir

__all__ = ["main", "command", "cache_dir"]


class UsageError(ValueError):
    """Bad command-line input (exit status 2)."""


def _parse_value(text: str):
    """A ``--set`` value in TOML syntax; a bare word is a string.

    Raises:
        UsageError: a value that starts like a TOML array, table or string but is not
            valid TOML (the TOML error is reported, not a type error later), or one nested
            too deeply.
    """
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # Python < 3.11
        import tomli as tomllib
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError as e:
        if text.lstrip().startswith(("[", "{", '"', "'")):
            raise UsageError(f"invalid TOML value {text!r}: {e}") from None
        return text
    except RecursionError:
        raise UsageError(f"the value {text[:40]!r}... is nested too deeply") from None


def _parser() -> argparse.ArgumentParser:
    """The argument parser of every sub-command.

    Long because: one flat declaration of the sub-commands and their options reads better
    than the same declarations spread over helpers.
    """
    from . import __version__

    p = argparse.ArgumentParser(
        prog="jaxelastic",
        description="Differentiable finite-element elasticity in JAX: run scenes, check "
        "the autodiff mechanics.",
    )
    p.add_argument("--version", action="version", version=f"jaxelastic {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    r = sub.add_parser(
        "run",
        help="run a scene (default: the built-in beam) and write its outputs",
        description="Solve a scene and write a ParaView time series (VTU + PVD), PNG "
        "pictures and summary.json into --out.",
    )
    r.add_argument(
        "scene",
        nargs="?",
        default="default",
        help="a scene TOML file or a shipped scene name (default: %(default)s)",
    )
    r.add_argument(
        "--out",
        "-o",
        default=None,
        metavar="DIR",
        help="output directory, created if needed (default: ./jaxelastic-out/<scene name>)",
    )
    r.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a scene entry, e.g. --set integrator.duration=1.0 (TOML value)",
    )
    r.add_argument("--no-progress", action="store_true", help="no progress bar or messages")
    r.add_argument(
        "--no-cache", action="store_true", help="do not use the persistent compilation cache"
    )
    r.add_argument(
        "--json",
        action="store_true",
        help="print one JSON line (status, output directory, timings) instead of the table",
    )
    f = sub.add_parser(
        "fit",
        help="fit E and nu to observed shapes as the scene's [fit] section says",
        description="Identify (E, nu) from observed (or synthetic) deformed shapes of a "
        "static scene with a [fit] section; writes summary.json, fit.png and observed.npz "
        "into --out. (`jaxelastic run` on a scene with [fit] does the same.)",
    )
    f.add_argument("scene", help="a scene TOML file with a [fit] section, or a shipped scene name")
    f.add_argument("--out", "-o", default=None, metavar="DIR", help="output directory")
    f.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a scene entry, e.g. --set fit.max_iter=20 (TOML value)",
    )
    f.add_argument("--no-progress", action="store_true", help="no progress bar or messages")
    f.add_argument("--no-cache", action="store_true", help="no persistent compilation cache")
    f.add_argument(
        "--json",
        action="store_true",
        help="print one JSON line (status, output directory, E, nu) instead of the table",
    )
    u = sub.add_parser(
        "unload",
        help="the unloaded rest shape of a static scene whose mesh is the loaded shape",
        description="Read the scene's mesh as the observed, loaded shape and find the rest "
        "shape whose equilibrium under the scene's loads and supports it is (inverse "
        "elastostatics); writes rest.vtu and summary.json into --out.",
    )
    u.add_argument("scene", help="a static scene TOML file or a shipped scene name")
    u.add_argument("--out", "-o", default=None, metavar="DIR", help="output directory")
    u.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    u.add_argument("--method", choices=("direct", "fixed_point"), default="direct")
    u.add_argument("--no-progress", action="store_true", help="no progress bar or messages")
    u.add_argument("--no-cache", action="store_true", help="no persistent compilation cache")
    u.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    sub.add_parser(
        "crosscheck",
        help="check autodiff stress/forces/HVP against hand derivations and finite "
        "differences (options: jaxelastic crosscheck --help)",
        add_help=False,
    )
    sub.add_parser("scenes", help="list the shipped scenes")
    sub.add_parser(
        "schema",
        help="print the JSON Schema of a scene file (jaxelastic schema > scene.schema.json)",
        description="Print the JSON Schema (draft 2020-12) of a scene file, for editors "
        "with TOML schema support (taplo / Even Better TOML: '#:schema ./scene.schema.json' "
        "on the first line of a scene file).",
    )
    return p


def _enable_jax(cache: bool) -> None:
    import jax

    from .cache import enable_persistent_cache, ensure_persistent_cache

    jax.config.update("jax_enable_x64", True)
    if not cache:
        ensure_persistent_cache(enable=False)  # the library's lazy default stays off too
        return
    try:
        enable_persistent_cache()
    except (OSError, RuntimeError) as e:
        print(f"jaxelastic: warning: no compilation cache ({e})", file=sys.stderr)


def _crosscheck(argv) -> int:
    try:
        from .verification import derivative_check as crosscheck
    except ImportError as e:
        print(f"jaxelastic: error: the crosscheck module is not available ({e})", file=sys.stderr)
        return 2
    return int(crosscheck.main(list(argv)) or 0)


def _list_scenes() -> int:
    from .scene import load_scene, shipped_scenes

    for name, path in shipped_scenes().items():
        try:
            desc = load_scene(path)["description"]
        except Exception as e:  # noqa: BLE001 — a broken shipped file is reported, not fatal
            desc = f"(invalid: {e})"
        print(f"{name:10s} {desc}\n{'':10s} {path}")
    return 0


def _print_schema() -> int:
    from .scene import json_schema

    print(json.dumps(json_schema(), indent=2))
    return 0


def _report(summary: dict, args, clock, t0: float, fit: bool = False) -> None:
    """Print the result of a run or fit on stdout: the table for people, or with
    ``--json`` one JSON line (status, out, summary path, timings; E and nu of a fit)."""
    from .scene.outputs import fit_table, run_table

    wall = time.perf_counter() - t0
    if getattr(args, "json", False):
        line = dict(
            status=summary["status"],
            out=summary["outputs"]["directory"],
            summary=summary["outputs"].get("summary"),
            wall_time=wall,
            compile_time=clock.seconds,
            warnings=summary.get("warnings", []),
        )
        if fit:
            line.update(E=summary["result"]["E"], nu=summary["result"]["nu"])
        print(json.dumps(line))
        return
    table = fit_table if fit else run_table
    print(table(summary, compile_s=clock.seconds, wall_s=wall))


SCENE_ADVICE = {
    1: "raise [solver] max_steps, apply the load in more steps ([integrator] load_steps, "
    "static) or take smaller time steps ([integrator] h, dynamic)",
    2: "apply the load in more steps ([integrator] load_steps) or set [solver] hessian = "
    '"projected"',
    3: "use an inversion-safe [material] model (stable_neo_hookean, fixed_corotated) or more "
    "load steps",
    4: 'check the scene\'s loads and material values for NaN/inf; [solver] precision = "float64"',
    5: '[solver] hessian = "projected" or linear = "direct"',
    6: '[solver] hessian = "projected", or Dirichlet conditions that hold the body',
}
"""What to change in a scene file for each failed :class:`~jaxelastic.solvers.Status`
(by value), printed under the Python-API advice of the :class:`SolveError`."""


def _run(args) -> int:
    from .scene import SceneError, load_scene

    overrides = {}
    for item in args.set:
        key, sep, val = item.partition("=")
        if not sep or not key.strip():
            print(f"jaxelastic: error: --set expects KEY=VALUE, got {item!r}", file=sys.stderr)
            return 2
        try:
            overrides[key.strip()] = _parse_value(val.strip())
        except UsageError as e:
            print(f"jaxelastic: error: --set {key.strip()}: {e}", file=sys.stderr)
            return 2
    _enable_jax(cache=not args.no_cache)
    from .scene import run_scene
    from .scene.outputs import CompileClock
    from .solvers import SolveError, SolveWarning

    t0 = time.perf_counter()
    clock = CompileClock()
    out, fresh = None, False
    try:
        scene = load_scene(args.scene, overrides=overrides)
        out = args.out or os.path.join("jaxelastic-out", scene.name)
        fresh = not os.path.exists(out)
        if args.command == "unload":
            return _unload(scene, out, args)
        if args.command == "fit" or scene.get("fit") is not None:
            return _fit(scene, out, args, t0, clock)
        with clock, warnings.catch_warnings():
            # the summary table lists the run's warnings (a loud row each)
            warnings.simplefilter("ignore", SolveWarning)
            summary = run_scene(scene, out, progress=not args.no_progress)
    except SceneError as e:
        print(f"jaxelastic: error: {e}", file=sys.stderr)
        if out is not None and fresh:
            _remove_if_empty(out)
        return 2
    except SolveError as e:
        print(f"jaxelastic: solve failed: {e}", file=sys.stderr)
        hint = SCENE_ADVICE.get(int(e.status), "")
        if hint:
            print(f"jaxelastic: in the scene: {hint}", file=sys.stderr)
        return 1
    except OSError as e:  # e.g. an output directory that cannot be created or written
        print(f"jaxelastic: error: {e}", file=sys.stderr)
        return 2
    _report(summary, args, clock, t0)
    return 0


def _unload(scene, out: str, args) -> int:
    """``jaxelastic unload``: :func:`~jaxelastic.scene.unload.unload_scene`; exit status 1
    unless it converged."""
    import json

    from .scene.unload import unload_scene

    summary = unload_scene(scene, out, method=args.method)
    if args.json:
        print(json.dumps(dict(summary, out=out, residual_history=None)))
    else:
        print(
            f"{summary['method']}: {summary['status']} after {summary['iterations']} "
            f"iterations, round trip {summary['round_trip']:.1e}, largest displacement "
            f"{summary['max_displacement']:.4g}; wrote {out}/rest.vtu and summary.json"
        )
    return 0 if summary["status"] == "SUCCESS" else 1


def _fit(scene, out: str, args, t0: float, clock) -> int:
    """``jaxelastic fit`` (or ``run`` on a scene with ``[fit]``): see jaxelastic.scene.fit."""
    from .scene import SceneError
    from .scene.fit import run_fit
    from .solvers import GradientError, SolveError

    fresh = not os.path.exists(out)
    try:
        with clock:
            summary = run_fit(scene, out, progress=not args.no_progress)
    except SceneError as e:
        print(f"jaxelastic: error: {e}", file=sys.stderr)
        if fresh:
            _remove_if_empty(out)
        return 2
    except (SolveError, GradientError) as e:
        print(f"jaxelastic: fit failed: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"jaxelastic: error: {e}", file=sys.stderr)
        return 2
    _report(summary, args, clock, t0, fit=True)
    return 0


def _remove_if_empty(out: str) -> None:
    """Remove the output directory this command created for a scene refused after all (a
    refused scene leaves nothing behind)."""
    with contextlib.suppress(OSError):
        if os.path.isdir(out) and not os.listdir(out):
            os.rmdir(out)


def _interrupted(e: KeyboardInterrupt) -> int:
    """One line for an interrupted run; exit status 130."""
    name = getattr(e, "signame", "SIGINT")
    detail, out = getattr(e, "detail", ""), getattr(e, "out", None)
    where = f" {detail}" if detail else ""
    if out is None:
        print(f"jaxelastic: interrupted by {name}{where}; nothing was written", file=sys.stderr)
    else:
        print(
            f"jaxelastic: interrupted by {name}{where}; partial results in {out} "
            '(summary.json: "interrupted": true)',
            file=sys.stderr,
        )
    return 130


def _run_interruptible(args) -> int:
    """``run``/``fit`` with SIGINT/SIGTERM stopping at the next step boundary."""
    try:
        from .scene.interrupt import handle_signals

        with handle_signals():
            return _run(args)
    except KeyboardInterrupt as e:  # scene.interrupt.Interrupted, or Ctrl-C while starting
        return _interrupted(e)


def command() -> NoReturn:
    """The ``jaxelastic`` console script: :func:`main`, then a prompt process exit.

    Every output is written and closed by then (atomic renames) and the ``atexit``
    handlers run, but the interpreter's own teardown (freeing the compiled programs, the
    XLA client and every module) is skipped: it took 0.5 s after a twist n = 29 run.
    """
    rc = main()
    # a signal from now on would only cut the exit handlers (and print their traceback)
    with contextlib.suppress(ValueError, OSError):  # (not the main thread)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(rc)


def _early_stop(signum, frame) -> None:
    """SIGINT/SIGTERM before the run's own handlers are installed (while JAX, SciPy and
    the scene modules import): stop with the usual one-line message."""
    e = KeyboardInterrupt()
    e.signame = signal.Signals(signum).name  # type: ignore[attr-defined]
    raise e


def main(argv=None) -> int:
    """Entry point of the ``jaxelastic`` command; returns the exit status.

    SIGINT and SIGTERM are handled from the start (exit status 130 and one line, never a
    traceback); a closed stdout (``jaxelastic schema | head``) ends the command quietly.
    """
    previous = {}
    try:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                previous[sig] = signal.signal(sig, _early_stop)
        return _main(argv)
    except KeyboardInterrupt as e:
        return _interrupted(e)
    except BrokenPipeError:  # the reader of stdout went away: nothing more to say
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 0
    finally:
        for sig, h in previous.items():
            with contextlib.suppress(ValueError, OSError, TypeError):
                signal.signal(sig, h)


def _main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "crosscheck":
        return _crosscheck(argv[1:])
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if args.command == "scenes":
        return _list_scenes()
    if args.command == "schema":
        return _print_schema()
    from .solvers.host import map_large_blocks

    map_large_blocks()  # freed large blocks back to the OS at once (process-wide)
    return _run_interruptible(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
