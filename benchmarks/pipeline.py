"""The stage times of ``spdslam run`` on a real recording, this checkout against an older
commit, side by side in one run (docs/performance.md, "The whole pipeline").

Each measurement is a fresh process that runs ``spdslam run SEQ --out TMP --overwrite`` as
the command line does (``spdslam.cli.app``), with ``PYTHONPATH`` pointing at the checkout
being measured and its own JAX compilation cache (``SPDSLAM_CACHE_DIR``):

- *empty cache*: the cache directory is new (every program is traced, lowered and
  compiled);
- *warm cache*: the same directory after that run (programs are traced and lowered, and
  their compiled code is loaded from disk).

The stages are timed by wrapping the pipeline's functions where they are defined, before any
other module imports them (an import hook), so the same driver times both checkouts without
changing either; a stage whose function an older commit does not have shows "–". Times are
inclusive (a stage's inner stages are part of it): import (``import spdslam.cli``), read,
screening, association, initialisation, graph (every ``build_graph``), each optimisation
(``Optimizer.optimize``; the first includes tracing and compilation), of which the first
linearisation and the sparsity pattern of H (``Problem.sparse_pattern``, all calls),
uncertainty, write (the run folder: map.json, report, figures), the XLA programs compiled or
loaded from the cache (``jax._src.compiler.compile_or_get_cached``: seconds, and their
number), the garbage collector's passes (``gc.callbacks``, every generation: seconds) and the
whole process (wall).
The older commit runs in a ``git worktree`` removed afterwards; both checkouts' modules are
compiled to bytecode first (as ``install.sh`` does), so that neither pays Python's compiler
where ``PYTHONDONTWRITEBYTECODE`` is set; the two checkouts alternate,
``--repeats`` times each, and the table gives medians and the ratio. ``--tables`` prints the
tables of an earlier ``--out`` file again. Before them, ``spdslam --help`` and ``spdslam run
--help`` are timed the same way (wall time of a fresh process, median of ``--help-repeats``).

    python3 benchmarks/pipeline.py --against d63919a
    python3 benchmarks/pipeline.py --against d63919a --repeats 3 --out benchmarks/results/pipeline.json
    python3 benchmarks/pipeline.py --sequence ../shared/data/tum_fr3_cabinet --no-empty
    python3 benchmarks/pipeline.py --tables benchmarks/results/pipeline.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
FR2 = ROOT / ".." / "shared" / "data" / "tum_fr2_desk"

#: Stages: (name, [(module, attribute), …]): the first that exists is timed.
STAGES = [
    ("read", [("spdslam.io._formats", "read_sequence")]),
    ("screening", [("spdslam.frontend._screening", "screen_detections")]),
    ("association", [("spdslam.frontend._association", "associate_detailed")]),
    ("initialisation", [("spdslam.mapping._run", "initialize_objects")]),
    ("graph", [("spdslam.mapping._graph", "build_graph")]),
    ("optimisation", [("spdslam.solver._optimizers", "Optimizer.optimize")]),
    ("linearisation", [("spdslam.solver._problem", "Problem.linearize")]),
    ("sparsity pattern", [("spdslam.solver._problem", "Problem.sparse_pattern")]),
    ("uncertainty", [("spdslam.mapping._run", "object_uncertainty")]),
    ("write", [("spdslam.experiments._run_folder", "write_run"),
               ("spdslam.evaluation._report", "write_run")]),
    ("XLA programs", [("jax._src.compiler", "compile_or_get_cached")]),
]

#: The driver run in each measured process: argv = [stages.json, output.json, cli args…].
DRIVER = r'''
import importlib.abc, importlib.util, json, sys, time
t_start = time.perf_counter()
stages, result_path = json.load(open(sys.argv[1])), sys.argv[2]
calls = {}
targets = {}
for name, options in stages:
    for module, attr in options:
        targets.setdefault(module, []).append((name, attr))

def wrap(name, fn):
    depth = [0]
    def timed(*a, **k):
        if depth[0]:
            return fn(*a, **k)
        depth[0] += 1
        t0 = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            depth[0] -= 1
            calls.setdefault(name, []).append(time.perf_counter() - t0)
    timed.__wrapped__ = fn
    for a in ("__name__", "__qualname__", "__doc__", "__module__"):
        setattr(timed, a, getattr(fn, a, None))
    return timed

done = set()

class Hook(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path, target=None):
        if fullname not in targets:
            return None
        sys.meta_path.remove(self)
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            sys.meta_path.insert(0, self)
        if spec is None or spec.loader is None:
            return None
        loader = spec.loader
        class Loader(importlib.abc.Loader):
            def create_module(self, s):
                return loader.create_module(s)
            def exec_module(self, module):
                loader.exec_module(module)
                for name, attr in targets[fullname]:
                    if name in done:
                        continue
                    owner, _, leaf = attr.rpartition(".")
                    obj = getattr(module, owner) if owner else module
                    fn = getattr(obj, leaf, None)
                    if fn is not None:
                        setattr(obj, leaf, wrap(name, fn))
                        done.add(name)
        spec.loader = Loader()
        return spec

sys.meta_path.insert(0, Hook())
import gc
_began = []
def _collector(phase, info):  # the garbage collector's passes, every generation
    if phase == "start":
        _began.append(time.perf_counter())
    else:
        calls.setdefault("collector", []).append(time.perf_counter() - _began.pop())
gc.callbacks.append(_collector)
t0 = time.perf_counter()
from spdslam.cli import app
t_import = time.perf_counter() - t0
sys.argv = ["spdslam"] + sys.argv[3:]
status = 0
try:
    app(standalone_mode=False)
except SystemExit as e:
    status = e.code or 0
import spdslam
out = {"import": t_import, "status": status, "wall_in_process": time.perf_counter() - t_start,
       "spdslam": spdslam.__path__[0]}
for name in [n for n, _ in stages] + ["collector"]:
    if name in calls:
        out[name] = calls[name]
json.dump(out, open(result_path, "w"))
'''


def measure(checkout: Path, seq: Path, cache: Path, work: Path, extra: list) -> dict:
    """One ``spdslam run`` of ``seq`` by ``checkout`` in a fresh process: its stage times."""
    stages, result = work / "stages.json", work / "result.json"
    stages.write_text(json.dumps(STAGES))
    out = work / "run"
    env = dict(os.environ, PYTHONPATH=str(checkout), SPDSLAM_CACHE_DIR=str(cache))
    cmd = [sys.executable, "-c", DRIVER, str(stages), str(result), "run", str(seq), "--out",
           str(out), "--overwrite", *extra]
    t0 = time.perf_counter()
    # run in the checkout: ``python -c`` puts the working directory first on sys.path
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=checkout)
    wall = time.perf_counter() - t0
    if proc.returncode != 0 or not result.exists():
        raise SystemExit(f"pipeline.py: {checkout} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    rec = json.loads(result.read_text())
    if Path(rec["spdslam"]).resolve() != (checkout / "spdslam").resolve():
        raise SystemExit(f"pipeline.py: measured {rec['spdslam']}, not {checkout}")
    if rec["status"]:
        raise SystemExit(f"pipeline.py: spdslam run exited {rec['status']} in {checkout}:\n{proc.stderr[-3000:]}")
    rec["wall"] = wall
    rec["map"] = json.loads((out / "map.json").read_text())
    rec["map"]["trajectory"] = np.loadtxt(out / "trajectory.txt").tolist()
    result.unlink()
    return rec


def time_help(checkout: Path, args: list, repeats: int) -> float:
    """Median wall time of ``spdslam ARGS`` (a help) in a fresh process of ``checkout``."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    code = "import sys; from spdslam.cli import app; sys.argv = ['spdslam'] + sys.argv[1:]; app()"
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, check=True, cwd=checkout)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def summarise(recs: list) -> dict:
    """Median over repeats of each stage (a stage called several times: their sum; the
    optimisations also one by one, the linearisations as the first and the rest)."""
    out: dict = {}
    keys = ["import", "read", "screening", "association", "initialisation", "graph",
            "optimisation", "sparsity pattern", "uncertainty", "write", "XLA programs", "collector", "wall"]
    for k in keys:
        vals = [sum(r[k]) if isinstance(r.get(k), list) else r.get(k) for r in recs]
        if k in ("XLA programs", "collector"):  # none: no call recorded
            vals = [v or 0.0 for v in vals]
        out[k] = statistics.median(vals) if all(v is not None for v in vals) else None
    out["XLA programs (number)"] = statistics.median(len(r.get("XLA programs") or []) for r in recs)
    n_opt = min(len(r.get("optimisation", [])) for r in recs)
    for i in range(n_opt):
        out[f"optimisation {i + 1}"] = statistics.median(r["optimisation"][i] for r in recs)
    if all(r.get("linearisation") for r in recs):
        out["first linearisation"] = statistics.median(r["linearisation"][0] for r in recs)
        out["other linearisations (mean)"] = statistics.median(
            statistics.fmean(r["linearisation"][1:] or [0.0]) for r in recs)
    return out


def print_tables(table: dict, names: list) -> None:
    """The stage tables (empty and warm cache) of ``table`` {checkout: {kind: summary}}."""
    for kind in ("empty", "warm"):
        if not all(kind in table[n] for n in names):
            continue
        rows = list(dict.fromkeys(k for n in names for k in table[n][kind]))
        head = f"| stage ({kind} cache, s) | " + " | ".join(names)
        head += " | ratio |" if len(names) == 2 else " |"
        print(head)
        print("| --- " * (len(names) + 1 + (len(names) == 2)) + "|")
        for k in rows:
            vals = [table[n][kind].get(k) for n in names]
            cells = ["–" if v is None else f"{v:.2f}" for v in vals]
            if len(names) == 2:
                a, b = vals
                cells.append(f"{a / b:.2f}×" if a is not None and b else "–")
            print(f"| {k} | " + " | ".join(cells) + " |")
        print()


def same_maps(a: dict, b: dict, tol: float = 1e-9) -> str:
    """"equal" when the two map.json documents' objects agree to ``tol``, else what differs."""
    oa, ob = a.get("objects", []), b.get("objects", [])
    if [o["id"] for o in oa] != [o["id"] for o in ob]:
        return f"different objects ({len(oa)} vs {len(ob)})"
    worst = max((float(np.max(np.abs(np.subtract(x[key], y[key]))))
                 for x, y in zip(oa, ob) for key in ("center", "P")), default=0.0)
    ta, tb = np.asarray(a["trajectory"]), np.asarray(b["trajectory"])
    if ta.shape != tb.shape:
        return f"trajectories of different lengths ({len(ta)} vs {len(tb)})"
    worst_t = float(np.max(np.abs(ta - tb))) if ta.size else 0.0
    if worst <= tol and worst_t <= tol:
        return f"equal to {tol:g} (objects and trajectory)"
    return f"objects differ by up to {worst:.2e}, trajectory rows by up to {worst_t:.2e}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=FR2)
    ap.add_argument("--against", default=None, help="an older commit to measure beside this checkout")
    ap.add_argument("--repeats", type=int, default=2, help="warm-cache runs per checkout")
    ap.add_argument("--no-empty", action="store_true", help="skip the empty-cache runs")
    ap.add_argument("--help-repeats", type=int, default=5, help="runs of each help timed (0: none)")
    ap.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    ap.add_argument("--tables", type=Path, default=None,
                    help="print the tables of a JSON file written by --out, and nothing else")
    ap.add_argument("extra", nargs="*", help="more options for spdslam run (after --)")
    args = ap.parse_args()
    if args.tables:  # the tables of an earlier run, summarised again (e.g. with a new stage)
        runs = json.loads(args.tables.read_text())["runs"]
        print_tables({name: {kind: summarise(r) for kind, r in by.items() if r} for name, by in runs.items()},
                     list(runs))
        return
    args.sequence = args.sequence.resolve()
    if not args.sequence.exists():
        raise SystemExit(f"pipeline.py: {args.sequence} does not exist")
    tmp = Path(tempfile.mkdtemp(prefix="spdslam_pipeline_"))
    checkouts = {"this checkout": ROOT}
    try:
        if args.against:
            wt = tmp / "against"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(wt), args.against],
                           check=True, capture_output=True)
            checkouts[args.against] = wt
        for path in checkouts.values():  # both as install.sh leaves them: modules compiled to bytecode
            subprocess.run([sys.executable, "-m", "compileall", "-q", str(path / "spdslam")], check=True,
                           capture_output=True)
        helps: dict = {}
        if args.help_repeats:
            for label, cli in (("spdslam --help", ["--help"]), ("spdslam run --help", ["run", "--help"])):
                helps[label] = {name: time_help(path, cli, args.help_repeats) for name, path in checkouts.items()}
            names = list(checkouts)
            print("| help (s, median of %d) | " % args.help_repeats + " | ".join(names)
                  + (" | ratio |" if len(names) == 2 else " |"))
            print("| --- " * (len(names) + 1 + (len(names) == 2)) + "|")
            for label, by in helps.items():
                vals = [by[n] for n in names]
                cells = [f"{v:.2f}" for v in vals] + ([f"{vals[0] / vals[1]:.2f}×"] if len(vals) == 2 else [])
                print(f"| {label} | " + " | ".join(cells) + " |")
            print(flush=True)
        recs: dict = {name: {"empty": [], "warm": []} for name in checkouts}
        caches = {name: tmp / f"cache_{i}" for i, name in enumerate(checkouts)}
        works = {name: tmp / f"work_{i}" for i, name in enumerate(checkouts)}
        for d in (*caches.values(), *works.values()):
            d.mkdir()
        for round_ in range(args.repeats + (0 if args.no_empty else 1)):
            for name, path in checkouts.items():
                work = works[name]
                kind = "empty" if (round_ == 0 and not args.no_empty) else "warm"
                if kind == "warm" and round_ == 0:  # --no-empty: warm the cache first, untimed
                    measure(path, args.sequence, caches[name], work, args.extra)
                t0 = time.perf_counter()
                rec = measure(path, args.sequence, caches[name], work, args.extra)
                recs[name][kind].append(rec)
                print(f"{name} ({kind} cache): {rec['wall']:.1f} s  [{time.perf_counter() - t0:.0f} s]",
                      flush=True)
        table = {name: {kind: summarise(r) for kind, r in by.items() if r} for name, by in recs.items()}
        names = list(checkouts)
        print()
        print_tables(table, names)
        if args.against:
            a = recs[names[0]]["warm"][-1]["map"]
            b = recs[names[1]]["warm"][-1]["map"]
            print(f"map.json objects, this checkout against {args.against}: {same_maps(a, b)}")
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            for by in recs.values():
                for rs in by.values():
                    for r in rs:
                        r.pop("map", None)
            args.out.write_text(json.dumps({"sequence": str(args.sequence), "help": helps, "table": table,
                                            "runs": recs},
                                           indent=1))
            print(f"wrote {args.out}")
    finally:
        if args.against:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tmp / "against")],
                           capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
