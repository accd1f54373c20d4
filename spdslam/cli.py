"""The ``spdslam`` command-line tool.

A single typer application, :data:`app`.  Commands are plain functions registered with
``@app.command()``; further commands (``simulate``, ``run``, ``evaluate``, ``demo``) are
added the same way.  Conventions for commands:

* bad user input -> :func:`fail` (one line on stderr, exit status 2);
* heavy imports (solver, factors, matplotlib, ...) go *inside* the command function, so
  that ``spdslam --help`` and ``spdslam --version`` stay fast;
* rich output goes through :data:`console` (stdout) / :data:`err_console` (stderr).

Before any command runs, :func:`main` (the app callback) enables JAX's persistent
compilation cache in ``$SPDSLAM_CACHE_DIR`` (default ``~/.cache/spdslam/jax``) so that
repeated runs skip most of the XLA compilation time.
"""

from __future__ import annotations

import math
import os
import platform
import sys
from importlib import metadata
from pathlib import Path
from typing import NoReturn

import typer
from rich.console import Console
from rich.table import Table

from ._version import __version__

#: Environment variable naming the JAX compilation-cache directory.
CACHE_ENV = "SPDSLAM_CACHE_DIR"
#: Default JAX compilation-cache directory.
DEFAULT_CACHE_DIR = Path("~/.cache/spdslam/jax")
#: Only compilations that took at least this long are written to the persistent cache.
CACHE_MIN_COMPILE_SECS = 0.1

app = typer.Typer(
    name="spdslam",
    help="Object-level SLAM back end: ellipsoid landmarks on SPD(3) x R^3.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)

console = Console()
err_console = Console(stderr=True)

#: Set by :func:`main`: the cache directory in use, or ``None`` if the cache is off.
_cache_dir_in_use: Path | None = None


# --------------------------------------------------------------------------- helpers


def fail(message: str, code: int = 2) -> NoReturn:
    """Report a bad-input error as one line on stderr and exit with ``code`` (default 2).

    Plain ``typer.echo`` rather than rich, so long messages are never wrapped.
    """
    text = " ".join(str(message).split())  # guarantee a single line
    typer.echo(f"spdslam: error: {text}", err=True)
    raise typer.Exit(code)


def cache_dir() -> Path:
    """The configured JAX compilation-cache directory (not necessarily existing)."""
    raw = os.environ.get(CACHE_ENV) or str(DEFAULT_CACHE_DIR)
    return Path(raw).expanduser()


def enable_compilation_cache(path: Path | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default :func:`cache_dir`).

    Returns the directory used, or ``None`` when it could not be created or configured;
    never raises.
    """
    path = cache_dir() if path is None else Path(path).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK):
            return None
    except OSError:
        return None
    try:
        import jax

        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_SECS)
    except Exception:  # noqa: BLE001 - the cache is an optimisation, never fatal
        return None
    return path


def cholmod_available() -> bool:
    """Whether scikit-sparse's CHOLMOD bindings import."""
    try:
        import sksparse.cholmod  # noqa: F401
    except Exception:  # noqa: BLE001 - ImportError or a broken shared library
        return False
    return True


def sparse_solver_name() -> str:
    """Human-readable name of the sparse linear solver the optimiser will use (as the
    solver itself decides: ``spdslam.solver.HAVE_CHOLMOD``)."""
    from .solver import HAVE_CHOLMOD

    if HAVE_CHOLMOD:
        return "CHOLMOD (scikit-sparse)"
    return "scipy.sparse (SuperLU)"


def _dist_version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(__version__)
        raise typer.Exit(0)


# --------------------------------------------------------------------------- app callback


@app.callback()
def main(
    version: bool = typer.Option(
        False,
        "--version",
        "-V",
        help="Print the spdslam version and exit.",
        callback=_version_callback,
        is_eager=True,
    ),
) -> None:
    """Object-level SLAM back end: ellipsoid landmarks on SPD(3) x R^3."""
    global _cache_dir_in_use
    _cache_dir_in_use = enable_compilation_cache()


# --------------------------------------------------------------------------- commands


@app.command()
def info() -> None:
    """Print versions, the sparse solver in use and the JAX backend."""
    import jax

    import spdslam  # noqa: F401 - enables float64 as a side effect

    versions = Table(title="spdslam environment", show_header=True, header_style="bold")
    versions.add_column("component")
    versions.add_column("value")
    versions.add_row("python", f"{platform.python_version()} ({sys.executable})")
    versions.add_row("spdslam", __version__)
    for dist in ("jax", "jaxlib", "jaxlie", "numpy", "scipy"):
        versions.add_row(dist, _dist_version(dist))
    has_cholmod = cholmod_available()
    versions.add_row(
        "cholmod",
        f"available (scikit-sparse {_dist_version('scikit-sparse')})"
        if has_cholmod
        else "not available",
    )
    versions.add_row("sparse solver", sparse_solver_name())
    try:
        backend = jax.default_backend()
        devices = ", ".join(str(d) for d in jax.devices())
    except Exception as exc:  # noqa: BLE001
        backend, devices = "unavailable", f"error: {exc}"
    versions.add_row("jax backend", backend)
    versions.add_row("jax devices", devices)
    versions.add_row("float64 (jax_enable_x64)", "enabled" if jax.config.jax_enable_x64 else "DISABLED")
    versions.add_row(
        "compilation cache",
        str(_cache_dir_in_use) if _cache_dir_in_use is not None else "off",
    )
    console.print(versions)



def _split(option: str, value: str, allowed=None, cast=str) -> tuple:
    items = tuple(x.strip() for x in value.split(",") if x.strip())
    if not items:
        fail(f"--{option}: expected a comma-separated list, got {value!r}")
    out = []
    for x in items:
        if allowed is not None and x not in allowed:
            fail(f"--{option}: unknown value {x!r}; expected one of {', '.join(allowed)}")
        try:
            out.append(cast(x))
        except ValueError:
            fail(f"--{option}: {x!r} is not a number")
    return tuple(out)


@app.command()
def simulate(
    trials: int = typer.Option(24, min=1, help="Trials per (viewing range, noise) cell."),
    seed: int = typer.Option(0, help="Seed of the scene generator."),
    out: Path = typer.Option(Path("results"), "--out", help="Output folder."),
    params: str = typer.Option("F,S,O", help="Parameterisations: F Full, S Rot-Trans-Scale, O SPD(3)."),
    models: str = typer.Option("inv,semi", help="Box models: inv (inverse), semi (semi-inverse)."),
    angles: str = typer.Option("60,120", help="Viewing ranges in degrees."),
    noise: str = typer.Option("L,M,H", help="Noise levels (the paper's L, M, H)."),
    max_iters: int = typer.Option(100, "--max-iters", min=1, help="LM iteration budget."),
    optimize: str = typer.Option(
        "auto", help="XLA optimisation of the batched solver: auto (by work: off for small "
        "grids), yes (2-3x faster loops, about 0.8 s more compile per method; worth it "
        "with the compilation cache warm), no."),
) -> None:
    """Reproduce the paper's simulation study (Table II, Fig. 12) with batched solves.

    Writes OUT/trials.csv, OUT/table.md, OUT/convergence.png and OUT/summary.json.
    """
    cfg_kwargs = dict(
        trials=trials,
        seed=seed,
        params=_split("params", params, ("F", "S", "O")),
        models=_split("models", models, ("inv", "semi")),
        angles=_split("angles", angles, None, float),
        noise=_split("noise", noise, ("L", "M", "H")),
        max_iters=max_iters,
    )
    if optimize not in ("auto", "yes", "no"):
        fail(f"--optimize: expected auto, yes or no, got {optimize!r}")
    cfg_kwargs["optimize"] = {"auto": None, "yes": True, "no": False}[optimize]
    if any(not 0 < a <= 360 for a in cfg_kwargs["angles"]):
        fail("--angles: each viewing range must be in (0, 360] degrees")
    if out.exists() and not out.is_dir():
        fail(f"--out: {out} exists and is not a folder")

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from .study import StudyConfig, run_study, write_outputs

    cfg = StudyConfig(**cfg_kwargs)
    n_struct = len(cfg.models) * len(cfg.params)
    console.print(
        f"simulate: {len(cfg.cells)} cells x {cfg.trials} trials x {n_struct} methods "
        f"= {len(cfg.cells) * cfg.trials * n_struct} solves"
    )
    with Progress(
        TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(), console=console, transient=False,
    ) as bar:  # fmt: skip
        task = bar.add_task("scenes", total=n_struct + 1)

        def progress(stage: str, done: int, total: int) -> None:
            bar.update(task, completed=done, description=f"solved {stage}" if done > 1 else stage)

        result = run_study(cfg, progress)
    summary = write_outputs(result, out)
    t = summary["timings"]
    console.print((out / "table.md").read_text())
    console.print(
        f"wall {t['wall']:.2f} s, {t['us_per_problem_iteration']:.1f} µs per problem-iteration; "
        f"wrote {out}/trials.csv, table.md, convergence.png, summary.json"
    )


# --------------------------------------------------------------------------- sequences

_SIGMA_HELP = (
    "Override a sigma, NAME=VALUE, repeatable (e.g. inverse_box=3); names in "
    "docs/sequences.md."
)


def _load_sequence(path: Path):
    from .sequence import SequenceFormatError, read_sequence

    try:
        return read_sequence(path)
    except SequenceFormatError as e:
        fail(str(e))


def _parse_sigmas(items) -> dict:
    from .mapping import DEFAULT_MAPPING_SIGMAS

    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or name.strip() not in DEFAULT_MAPPING_SIGMAS:
            fail(f"--sigma: expected NAME=VALUE with NAME one of {', '.join(sorted(DEFAULT_MAPPING_SIGMAS))}, got {item!r}")
        try:
            v = float(value)
        except ValueError:
            fail(f"--sigma: {value!r} is not a number (in {item!r})")
        if not (math.isfinite(v) and (v > 0 or (v == 0 and name.strip() == "inverse_box_relative"))):
            fail(f"--sigma: expected a finite positive value, got {item!r}")
        out[name.strip()] = v
    return out


def _print_metrics(metrics: dict) -> None:
    s = metrics.get("summary")
    if s:
        console.print(
            f"mean IoU {s['mean_iou']:.3f}, orientation error {s['mean_orientation_deg']:.2f}°, "
            f"centre error {s['mean_center_error']:.3f} m ({s['matched']}/{s['ground_truth_objects']} objects)"
        )
    if "ate" in metrics:
        a = metrics["ate"]
        console.print(f"ATE RMSE: input {a['input']['rmse']:.4f} m, optimised {a['optimized']['rmse']:.4f} m")


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        fail(f"--out: {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        fail(f"--out: {out} exists and is not empty (use --overwrite)")


def _parse_robust(items, robust_k):
    """``--robust`` values: KERNEL (box and measured-ellipsoid factors, threshold
    ``--robust-k``) or TYPE=KERNEL[:K] (one factor type) -> Method overrides."""
    from .mapping import ROBUST_FACTOR_TYPES, ROBUST_KERNELS

    out, by_type = {}, []
    for item in items or []:
        ftype, sep, rest = item.partition("=")
        if not sep:
            ftype, rest = None, item
        name, colon, k = rest.partition(":")
        try:
            k = float(k) if colon else (robust_k if robust_k is not None else 1.0)
        except ValueError:
            fail(f"--robust: {k!r} is not a number (in {item!r})")
        if (ftype is not None and ftype not in ROBUST_FACTOR_TYPES) or name not in ROBUST_KERNELS \
                or not (math.isfinite(k) and k > 0):
            fail(f"--robust: expected KERNEL or TYPE=KERNEL[:K] with KERNEL one of {', '.join(ROBUST_KERNELS)}, "
                 f"TYPE one of {', '.join(ROBUST_FACTOR_TYPES)} and K > 0, got {item!r}")
        if ftype is None:
            out["robust"], out["robust_k"] = name, k
        else:
            by_type.append((ftype, name, k))
    if by_type:
        out["robust_by_type"] = tuple(by_type)
    return out


def _run_and_write(seq, method, out, overwrite, overlay, sigmas, max_iterations, associate=None,
                   **overrides):
    from .mapping import run_sequence
    from .report import write_run

    _check_out(out, overwrite)
    try:
        result = run_sequence(seq, method, sigmas=sigmas, max_iterations=max_iterations,
                              associate=associate, **overrides)
    except ValueError as e:
        fail(f"{seq.name}: {e}")
    try:
        metrics = write_run(out, seq, result, overlay=overlay, overwrite=overwrite)
    except FileExistsError as e:
        fail(f"--out: {e}")
    console.print(
        f"{result.method.name}: {len(result.objects)} objects, {result.iterations} iterations "
        f"({result.reason}), cost {result.initial_cost:.6g} -> {result.final_cost:.6g}"
    )
    for k, why in result.failed.items():
        err_console.print(f"object {k} not mapped: {why}")
    a = result.association
    if a.get("mode") == "auto":
        scores = (f": precision {a['precision']:.3f}, recall {a['recall']:.3f} against the instance ids"
                  if "precision" in a else "")
        console.print(f"automatic data association, {len(result.objects) + len(result.failed)} tracks{scores}")
    _print_metrics(metrics)
    console.print(f"wrote {out}")
    return result, metrics


@app.command()
def run(
    sequence: Path = typer.Argument(..., help="Sequence folder (canonical format or fr3_cabinet layout)."),
    method: str = typer.Option("multi-spd", help="quadric-slam, multi-rts or multi-spd."),
    out: Path = typer.Option(Path("out"), "--out", help="Output folder."),
    parameterization: str | None = typer.Option(None, help="Override: spd, rts or full."),
    box_model: str | None = typer.Option(None, help="Override: inverse, semi or semi-then-inverse."),
    associate: str | None = typer.Option(None, help="Data association: instances (the instance column) or auto; default: instances when every detection has an id, else auto."),
    object_shape: str | None = typer.Option(None, help="Silhouette model: priors (per class, priors.yaml 'shape'), ellipsoid or cuboid."),
    truncation_margin: float | None = typer.Option(None, help="Box edges within this many px of the image border carry no bound (negative: keep all; default 5)."),
    robust: list[str] | None = typer.Option(None, help="Robust kernel, repeatable: KERNEL (none, huber, cauchy) on box and measured-ellipsoid factors, or TYPE=KERNEL[:K] for one factor type (box, ellipsoid, odometry, orientation, support_plane, shape, size)."),
    robust_k: float | None = typer.Option(None, help="Threshold of a plain --robust KERNEL (whitened units, default 1)."),
    sigma: list[str] | None = typer.Option(None, help=_SIGMA_HELP),
    max_iterations: int = typer.Option(100, min=1, help="LM iteration budget per stage."),
    overlay: bool = typer.Option(True, help="Write overlay/ frames when the sequence has images."),
    overwrite: bool = typer.Option(False, help="Replace a non-empty OUT."),
) -> None:
    """Map a sequence: initialise every object, optimise poses and objects jointly.

    Writes OUT/map.json, OUT/trajectory.txt, OUT/map_top.png, and with ground truth
    OUT/report.md and OUT/metrics.json, and with images OUT/overlay/.
    """
    from .mapping import METHODS

    if method not in METHODS:
        fail(f"--method: unknown method {method!r}; expected one of {', '.join(METHODS)}")
    sigmas = _parse_sigmas(sigma)
    robust_overrides = _parse_robust(robust, robust_k)
    if robust_k is not None and "robust" not in robust_overrides:
        robust_overrides["robust_k"] = robust_k
    if associate not in (None, "instances", "auto"):
        fail(f"--associate: expected instances or auto, got {associate!r}")
    if object_shape not in (None, "priors", "ellipsoid", "cuboid"):
        fail(f"--object-shape: expected priors, ellipsoid or cuboid, got {object_shape!r}")
    if truncation_margin is not None and not math.isfinite(truncation_margin):
        fail(f"--truncation-margin: expected a finite number of pixels, got {truncation_margin!r}")
    seq = _load_sequence(sequence)
    _run_and_write(seq, method, out, overwrite, overlay, sigmas, max_iterations, associate,
                   parameterization=parameterization, box_model=box_model,
                   object_shape=object_shape, truncation_margin=truncation_margin, **robust_overrides)


@app.command()
def evaluate(
    out: Path = typer.Argument(..., help="Output folder of spdslam run (or its map.json)."),
    sequence: Path = typer.Argument(..., help="The sequence folder with ground truth."),
) -> None:
    """Evaluate a map against a sequence's ground truth; prints and writes
    OUT/metrics.json and OUT/report.md."""
    import json

    import numpy as np

    from .report import MapFormatError, evaluate_run, read_map, report_markdown
    from .sequence import SequenceFormatError, _read_tum

    seq = _load_sequence(sequence)
    try:
        m, objects = read_map(out)
    except MapFormatError as e:
        fail(str(e))
    folder = out if out.is_dir() else out.parent
    traj = folder / "trajectory.txt"
    poses = None
    if traj.is_file():
        try:
            poses = _read_tum(traj, str(traj))
        except SequenceFormatError as e:
            fail(str(e))
    if not seq.objects_gt and seq.groundtruth_tum is None:
        fail(f"{sequence}: expected ground truth (objects_gt.txt or groundtruth.txt), got neither")
    if poses is None:
        poses = np.column_stack([seq.timestamps, seq.poses_tum])
    try:
        metrics = evaluate_run(m, objects, None, poses, seq)
        texts = {"metrics.json": json.dumps(metrics, indent=1) + "\n",
                 "report.md": report_markdown(metrics, m)}
    except (TypeError, ValueError, KeyError) as e:
        fail(f"{folder / 'map.json'}: expected a map written by spdslam run, got {type(e).__name__}: {e}")
    for name, text in texts.items():
        tmp = folder / f".{name}.tmp"
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, folder / name)
    for r in metrics.get("objects", []):
        console.print(f"object {r['id']} ({r['label']}): IoU {r['iou']:.3f}, orientation {r['orientation_deg']:.2f}°")
    _print_metrics(metrics)
    console.print(f"wrote {folder / 'metrics.json'} and {folder / 'report.md'}")


@app.command("import")
def import_(
    source: Path = typer.Argument(..., help="A TUM fr3_cabinet-style folder (bbox/, groundtruth.txt, TUM3.yaml, truth_objects.txt)."),
    dest: Path = typer.Argument(..., help="Destination folder (canonical format)."),
    overwrite: bool = typer.Option(False, help="Replace a non-empty DEST."),
) -> None:
    """Convert an fr3_cabinet-style folder to the canonical sequence format."""
    from .sequence import SequenceFormatError, import_fr3_cabinet, write_sequence

    if not source.is_dir():
        fail(f"{source}: expected an fr3_cabinet-style folder, got no such folder")
    try:
        seq = import_fr3_cabinet(source)
        write_sequence(seq, dest, overwrite=overwrite)
    except SequenceFormatError as e:
        fail(str(e))
    except FileExistsError as e:
        fail(f"{dest}: {e}")
    console.print(f"imported {len(seq)} poses, {len(seq.detections)} detections into {dest}")


@app.command()
def compare(
    sequence: Path = typer.Argument(..., help="Sequence folder with object ground truth."),
    out: Path = typer.Option(Path("compare"), "--out", help="Output folder (one sub-folder per method)."),
    methods: str = typer.Option("quadric-slam,multi-rts,multi-spd", help="Methods to run."),
    overwrite: bool = typer.Option(False, help="Replace non-empty outputs."),
) -> None:
    """Run several methods on one sequence and write a Table-III-like OUT/table.md."""
    from .mapping import METHODS
    from .report import FRONT_END_NAMES, table_iii

    names = _split("methods", methods, tuple(METHODS))
    seq = _load_sequence(sequence)
    if not seq.objects_gt:
        fail(f"{sequence}: expected object ground truth (objects_gt.txt) to compare methods, got none")
    _check_out(out, overwrite)
    rows, fronts = [], {}
    for name in names:
        result, metrics = _run_and_write(seq, name, out / name, overwrite, False, {}, 100)
        init = result.method.initialization
        if init not in fronts:
            fronts[init] = metrics["front_end"]["summary"]
        rows.append(("back end", name, metrics["summary"]))
    front_rows = [("front end", FRONT_END_NAMES[k], v) for k, v in fronts.items()]
    table = f"# {seq.name}\n\n" + table_iii(front_rows + rows)
    (out / "table.md").write_text(table, encoding="utf-8")
    console.print(table)


DEMO_MARKER = ".spdslam-demo"


@app.command()
def demo(
    out: Path = typer.Option(Path("spdslam-demo"), "--out", help="Output folder (replaced if it holds an earlier demo)."),
    seed: int = typer.Option(0, help="Seed of the generator."),
    frames: int = typer.Option(120, min=3, help="Camera frames."),
    objects: int = typer.Option(8, min=1, help="Objects in the room."),
    method: str = typer.Option("multi-spd", help="quadric-slam, multi-rts or multi-spd."),
    truncation: bool = typer.Option(False, "--truncation/--no-truncation", help="Keep objects partly outside the image (boxes clipped to it)."),
    outliers: float = typer.Option(0.0, help="False detections (instance -1), as a fraction of the true ones, in [0, 1)."),
    missed: float = typer.Option(0.0, help="Fraction of the true detections dropped, in [0, 1)."),
    cuboids: bool = typer.Option(False, "--cuboids", help="Box-shaped objects (boxes of their 8 projected corners)."),
    no_ids: bool = typer.Option(False, "--no-ids", help="Write the detections without the instance column (then mapped with automatic association)."),
    associate: str | None = typer.Option(None, help="Data association: instances or auto (default: auto with --no-ids, else instances)."),
) -> None:
    """The embedded default: generate a synthetic room sequence (OUT/sequence, canonical
    format) and map it with a method (OUT/run), end to end, without any download.

    With --no-ids the written detections have no instance column and the run uses automatic
    association (the generator's ids only score it: precision and recall)."""
    import dataclasses

    from .demo import make_room_sequence
    from .mapping import METHODS
    from .sequence import write_sequence

    if method not in METHODS:
        fail(f"--method: unknown method {method!r}; expected one of {', '.join(METHODS)}")
    if associate not in (None, "instances", "auto"):
        fail(f"--associate: expected instances or auto, got {associate!r}")
    if associate is None:
        associate = "auto" if no_ids else "instances"
    if no_ids and associate != "auto":
        fail("--associate: the detections have no instance ids (--no-ids): expected auto")
    if out.exists() and not out.is_dir():
        fail(f"--out: {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not (out / DEMO_MARKER).exists():
        fail(f"--out: {out} exists, is not empty and is not an earlier demo output")
    try:
        seq = make_room_sequence(
            seed, frames, objects, truncation=truncation, outliers=outliers, missed=missed,
            object_shape="cuboid" if cuboids else "ellipsoid",
        )
    except ValueError as e:
        fail(f"demo: {e}")
    n_false = sum(d.instance < 0 for d in seq.detections)
    scored_seq = seq
    if no_ids:
        seq = dataclasses.replace(
            seq, detections=[dataclasses.replace(d, instance=None) for d in seq.detections]
        )
    out.mkdir(parents=True, exist_ok=True)
    (out / DEMO_MARKER).write_text("written by spdslam demo\n", encoding="utf-8")
    write_sequence(seq, out / "sequence", overwrite=True)
    console.print(
        f"demo: {len(seq)} frames, {len(seq.objects_gt)} objects, {len(seq.detections)} boxes "
        f"({n_false} false) -> {out / 'sequence'}"
    )
    # automatic association ignores the ids; the generator's (scored_seq) only score it
    _run_and_write(scored_seq, method, out / "run", True, False, {}, 100, associate)


if __name__ == "__main__":  # pragma: no cover
    app()
