"""Where the compile time of a ``jaxelastic run`` goes, and what the persistent cache saves.

Two measurements per scene (``--scenes default,twist``):

1. **Whole command**, ``python -m jaxelastic run SCENE --out TMP --no-progress`` as a
   subprocess, ``--repeat`` times (min reported) in three settings:

   * ``no cache``: ``--no-cache`` (every compilation from scratch);
   * ``cache, 1st run``: the persistent cache on, in a fresh empty directory (a cold run
     that also writes the cache);
   * ``cache, 2nd run``: the same command again on the filled directory (what a repeated
     run of a same-shaped scene costs).

   Each row: wall time [s], CPU time of the child (user + sys) [s], peak RSS [MB]
   (``os.wait4``), and the number of entries in the cache directory. On a loaded machine
   the CPU time is the steadier figure.

2. **Per compiled function** (one run of the CLI in a child process, no cache and 2nd run
   with cache): ``jax.monitoring`` duration events per function name — tracing (jaxpr),
   lowering (jaxpr → StableHLO) and XLA compilation (on a cache hit: the load of the cached
   executable) — plus the number of compilations, persistent-cache hits, whether JAX
   refused to cache it because it holds a host callback, and the size of the lowered
   StableHLO module (bytes and number of ops, from ``jax_dump_ir_to``).

Usage::

    python scripts/bench_compile.py [--scenes default,twist] [--repeat 3] [--set KEY=VALUE]
                                    [--out out/bench/compile.json] [--no-whole] [--no-profile]

Prints the tables and writes the JSON (``--out``). Run it on an idle machine: the figures
are wall-clock times of whole processes.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
COMPILE = "/jax/core/compile/backend_compile_duration"


# ----------------------------------------------------------------------------------------
# the child: one CLI run in-process with listeners
# ----------------------------------------------------------------------------------------


def _profile_child(argv: list[str], dump: str, result: str) -> int:
    """Run ``jaxelastic`` (``argv``) in this process, recording per-function compile events
    into the JSON file ``result``."""
    import logging

    import jax
    from jax import monitoring

    jax.config.update("jax_dump_ir_to", dump)
    jax.config.update("jax_dump_ir_modes", "stablehlo")
    per: dict[str, dict] = defaultdict(
        lambda: dict(trace_s=0.0, lower_s=0.0, compile_s=0.0, compiles=0, traces=0)
    )
    key = {TRACE: "trace_s", LOWER: "lower_s", COMPILE: "compile_s"}

    def on_duration(event: str, duration: float, **kw) -> None:
        if event in key:
            name = _short(str(kw.get("fun_name", "?")))
            per[name][key[event]] += duration
            if event == COMPILE:
                per[name]["compiles"] += 1
            if event == TRACE:
                per[name]["traces"] += 1

    monitoring.register_event_duration_secs_listener(on_duration)
    hits: dict[str, int] = defaultdict(int)
    refused: set[str] = set()

    class Capture(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            msg = record.getMessage()
            m = re.match(r"Persistent compilation cache hit for '([^']+)'", msg)
            if m:
                hits[_short(m.group(1))] += 1
            m = re.match(r"Not writing persistent cache entry for '([^']+)' because it uses h", msg)
            if m:
                refused.add(_short(m.group(1)))

    log = logging.getLogger("jax._src.compiler")
    log.setLevel(logging.DEBUG)
    log.addHandler(Capture())
    log.propagate = False

    from jaxelastic.cli import main

    t0 = time.perf_counter()
    rc = main(argv)
    wall = time.perf_counter() - t0
    sizes = _ir_sizes(dump)
    rows = []
    for name, d in per.items():
        size = sizes.get(name, dict(bytes=0, ops=0, modules=0))
        rows.append(
            dict(
                function=name,
                **{k: round(v, 4) if isinstance(v, float) else v for k, v in d.items()},
                cache_hits=hits.get(name, 0),
                host_callback=name in refused,
                stablehlo_bytes=size["bytes"],
                stablehlo_ops=size["ops"],
            )
        )
    rows.sort(key=lambda r: -(r["trace_s"] + r["lower_s"] + r["compile_s"]))
    Path(result).write_text(json.dumps(dict(rc=rc, wall_s=wall, functions=rows)))
    return rc


def _short(name: str) -> str:
    """``jit(_host_update)`` / ``jit__host_update`` / ``_host_update`` -> ``_host_update``."""
    m = re.fullmatch(r"jit\((.*)\)", name)
    if m:
        return m.group(1)
    return name[4:] if name.startswith("jit_") else name


def _ir_sizes(dump: str) -> dict[str, dict]:
    """Bytes and op count of the dumped StableHLO modules, per function (largest module)."""
    out: dict[str, dict] = {}
    for f in Path(dump).glob("*.mlir"):
        m = re.match(r"jax_ir\d+_(.*)_compile\.mlir$", f.name)
        if not m:
            continue
        name = _short(m.group(1))
        text = f.read_text()
        ops = len(re.findall(r"\b(?:stablehlo|chlo|mhlo)\.\w+", text))
        prev = out.get(name)
        if prev is None or len(text) > prev["bytes"]:
            out[name] = dict(bytes=len(text), ops=ops, modules=(prev or {}).get("modules", 0) + 1)
        else:
            prev["modules"] += 1
    return out


# ----------------------------------------------------------------------------------------
# the parent
# ----------------------------------------------------------------------------------------


def _command(scene: str, out: str, sets: list[str], cache: bool) -> list[str]:
    cmd = ["run", scene, "--out", out, "--no-progress"]
    for s in sets:
        cmd += ["--set", s]
    if not cache:
        cmd.append("--no-cache")
    return cmd


def _run_child(args: list[str], env: dict, cwd: str) -> dict:
    """Run ``python ARGS`` in ``cwd``; wall, CPU (user + sys) and peak RSS of the child.
    (The jaxelastic imported is the installed one, or the one on ``$PYTHONPATH``.)"""
    t0 = time.perf_counter()
    p = subprocess.Popen(
        [sys.executable, *args],
        env=env,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert p.stdout is not None and p.stderr is not None
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    out, err = p.stdout.read().decode(), p.stderr.read().decode()
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({p.returncode}):\n{out}\n{err[-3000:]}")
    return dict(
        wall_s=wall, cpu_s=ru.ru_utime + ru.ru_stime, peak_rss_mb=ru.ru_maxrss / 1024, stdout=out
    )


def _entries(d: str) -> int:
    return sum(1 for f in Path(d).glob("*") if f.is_file()) if os.path.isdir(d) else 0


def whole_command(scene: str, sets: list[str], repeat: int, tmp: str) -> list[dict]:
    """The three settings of the whole command, ``repeat`` runs each (min reported)."""
    rows = []
    out = os.path.join(tmp, "out")
    for setting in ("no cache", "cache, 1st run", "cache, 2nd run"):
        runs = []
        for i in range(repeat):
            cache = os.path.join(tmp, f"cache{i}")
            if setting == "cache, 1st run":
                shutil.rmtree(cache, ignore_errors=True)
            env = dict(os.environ, JAXELASTIC_CACHE_DIR=cache)
            cmd = ["-m", "jaxelastic", *_command(scene, out, sets, setting != "no cache")]
            r = _run_child(cmd, env, tmp)
            r["cache_entries"] = _entries(cache) if setting != "no cache" else 0
            runs.append(r)
            print(
                f"  {scene:8s} {setting:15s} run {i + 1}: {r['wall_s']:6.1f} s wall, "
                f"{r['cpu_s']:6.1f} s CPU",
                flush=True,
            )
        rows.append(
            dict(
                scene=scene,
                setting=setting,
                wall_s_min=min(r["wall_s"] for r in runs),
                cpu_s_min=min(r["cpu_s"] for r in runs),
                peak_rss_mb=max(r["peak_rss_mb"] for r in runs),
                cache_entries=runs[-1]["cache_entries"],
                wall_s_all=[round(r["wall_s"], 2) for r in runs],
            )
        )
    return rows


def profile(scene: str, sets: list[str], tmp: str, cache: str | None) -> dict:
    """Per-function compile figures of one CLI run in a child process."""
    dump = tempfile.mkdtemp(dir=tmp, prefix="ir")
    result = os.path.join(tmp, "profile.json")
    env = dict(os.environ)
    if cache is not None:
        env["JAXELASTIC_CACHE_DIR"] = cache
    argv = _command(scene, os.path.join(tmp, "out"), sets, cache is not None)
    r = _run_child([__file__, "--_child", dump, result, "--", *argv], env, tmp)
    prof = json.loads(Path(result).read_text())
    prof.update(cpu_s=r["cpu_s"], peak_rss_mb=r["peak_rss_mb"])
    shutil.rmtree(dump, ignore_errors=True)
    return prof


def _print_whole(rows: list[dict]) -> None:
    print(
        f"\n{'scene':8s} {'setting':15s} {'wall s (min)':>12s} {'CPU s (min)':>12s} "
        f"{'peak RSS MB':>12s} {'cache entries':>14s}"
    )
    for r in rows:
        print(
            f"{r['scene']:8s} {r['setting']:15s} {r['wall_s_min']:12.2f} {r['cpu_s_min']:12.2f} "
            f"{r['peak_rss_mb']:12.0f} {r['cache_entries']:14d}"
        )


def _print_profile(scene: str, label: str, prof: dict, top: int = 14) -> None:
    fns = prof["functions"]
    tot = {k: sum(f[k] for f in fns) for k in ("trace_s", "lower_s", "compile_s", "compiles")}
    print(
        f"\n{scene}, {label}: {len(fns)} functions, {tot['compiles']} XLA compilations "
        f"(trace {tot['trace_s']:.2f} s, lower {tot['lower_s']:.2f} s, "
        f"XLA {tot['compile_s']:.2f} s; command {prof['wall_s']:.1f} s wall, "
        f"{prof['cpu_s']:.1f} s CPU)"
    )
    print(
        f"  {'function':24s} {'n':>3s} {'trace s':>8s} {'lower s':>8s} {'XLA s':>8s} "
        f"{'hits':>5s} {'callback':>8s} {'HLO kB':>8s} {'HLO ops':>8s}"
    )
    for f in fns[:top]:
        print(
            f"  {f['function'][:24]:24s} {f['compiles']:3d} {f['trace_s']:8.2f} "
            f"{f['lower_s']:8.2f} {f['compile_s']:8.2f} {f['cache_hits']:5d} "
            f"{'yes' if f['host_callback'] else '':>8s} "
            f"{f['stablehlo_bytes'] / 1e3:8.0f} {f['stablehlo_ops']:8d}"
        )
    rest = fns[top:]
    if rest:
        s = sum(f["trace_s"] + f["lower_s"] + f["compile_s"] for f in rest)
        print(f"  ... {len(rest)} more (op-by-op and small functions): {s:.2f} s in all")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--_child"]:  # internal: the profiled child
        dump, result, _, *rest = argv[1:]
        return _profile_child(rest, dump, result)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--scenes", default="default,twist")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", default=str(ROOT / "out" / "bench" / "compile.json"))
    p.add_argument("--no-whole", action="store_true", help="skip the whole-command timings")
    p.add_argument("--no-profile", action="store_true", help="skip the per-function profile")
    a = p.parse_args(argv)
    import platform

    result: dict = dict(
        machine=f"{os.cpu_count()} cores, {platform.platform()}, "
        f"python {platform.python_version()}",
        load_average=os.getloadavg(),
        command="python -m jaxelastic run SCENE --out TMP --no-progress [--no-cache]",
        sets=a.set,
        whole=[],
        profiles={},
    )
    for scene in a.scenes.split(","):
        with tempfile.TemporaryDirectory(prefix="bench_compile_") as tmp:
            if not a.no_whole:
                result["whole"] += whole_command(scene, a.set, a.repeat, tmp)
            if not a.no_profile:
                cache = os.path.join(tmp, "pcache")
                shutil.rmtree(cache, ignore_errors=True)
                nc = profile(scene, a.set, tmp, None)
                profile(scene, a.set, tmp, cache)  # fills the cache
                warm = profile(scene, a.set, tmp, cache)
                result["profiles"][scene] = {"no cache": nc, "cache, 2nd run": warm}
                _print_profile(scene, "no cache", nc)
                _print_profile(scene, "cache, 2nd run", warm)
    if result["whole"]:
        _print_whole(result["whole"])
    result["load_average_end"] = os.getloadavg()
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    from jaxelastic.io import write_json  # atomic; imported late: the parent runs no JAX

    write_json(a.out, result)
    load = f"{result['load_average'][0]:.1f} -> {result['load_average_end'][0]:.1f}"
    print(f"\nwrote {a.out} (load average {load})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
