"""``spdslam simulate``: the paper's simulation study (Table II, Fig. 12)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import typer

from ._app import RAY_ADDRESS_HELP, RAY_HELP, RETRIES_HELP, WORKERS_HELP, app, check_output, console, fail, open_engine

__all__ = ["simulate", "split_option"]


def split_option(option: str, value: str, allowed=None, cast=str) -> tuple:
    """The items of a comma-separated option ``--option a,b,c``, each among ``allowed`` (when
    given) and converted by ``cast``; an empty list, an unknown item or one ``cast`` refuses
    exits with a one-line error (``fail``)."""
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


def _protocol(name, focal, distance, pattern, elevation, views):
    """The named protocol with the options' overrides, or a one-line error."""
    from ..synthetic import PROTOCOLS, get_protocol

    if name not in PROTOCOLS:
        fail(f"--protocol: expected one of {', '.join(PROTOCOLS)}, got {name!r}")
    rng = None
    if distance is not None:
        parts = distance.split("-")
        try:
            rng = tuple(float(x) for x in parts)
        except ValueError:
            rng = ()
        if len(rng) != 2:
            fail(f"--distance: expected LO-HI in metres (e.g. 4-6), got {distance!r}")
    try:
        return get_protocol(name).replace(focal=focal, distance=rng, pattern=pattern,
                                          elevation_deg=elevation, n_views=views)
    except ValueError as e:
        field = str(e).split(" ", 1)[0]
        option = {"focal": "focal", "distance": "distance", "pattern": "pattern",
                  "elevation_deg": "elevation", "n_views": "views"}.get(field, "protocol")
        fail(f"--{option}: {e}")


@app.command()
def simulate(
    trials: int = typer.Option(24, min=1, help="Trials per (viewing range, noise) cell."),
    seed: int = typer.Option(0, help="Seed of the scene generator."),
    out: Path = typer.Option(Path("results"), "--out", help="Output folder."),
    params: str = typer.Option("F,S,O", help="Parameterisations: F Full, S Rot-Trans-Scale, O SPD(3)."),
    models: str = typer.Option("inv,semi", help="Box models: inv (inverse), semi (semi-inverse)."),
    angles: str = typer.Option("60,120", help="Viewing ranges in degrees."),
    noise: str = typer.Option("L,M,H", help="Noise levels (the paper's L, M, H)."),
    max_iters: int = typer.Option(200, "--max-iters", min=1, help="Iteration budget."),
    protocol: str = typer.Option(
        "paper", help="The scenes' protocol: paper (calibrated to the paper's method-independent "
        "figures, docs/simulation.md) or v1 (the study until issue 16: f = 500 px)."),
    focal: float = typer.Option(None, help="Override the protocol's focal length (px; the image "
                                "keeps the 640 x 480 / f = 500 field of view)."),
    distance: str = typer.Option(None, help="Override the camera distance range, LO-HI metres."),
    pattern: str = typer.Option(None, help="Override the viewing pattern: cone or arc."),
    elevation: float = typer.Option(None, help="Override the elevation spread (± degrees)."),
    views: int = typer.Option(None, help="Override the number of views (≥ 3; the paper: 10)."),
    optimizer: str = typer.Option(
        "lm", help="The solver: lm (Levenberg-Marquardt) or dogleg (Powell's dogleg)."),
    optimize: str = typer.Option(
        "auto", help="XLA optimisation of the batched solver: auto (by work: off for small "
        "grids), yes (faster loops for a longer compile; worth it with the compilation "
        "cache warm: docs/performance.md), no."),
    ray: bool = typer.Option(False, "--ray", help=RAY_HELP),
    ray_address: str | None = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP),
    workers: int | None = typer.Option(None, min=1, help=WORKERS_HELP),
    trials_per_task: int | None = typer.Option(
        None, min=1, help="--ray: problems per task (default: each method's problems in twice "
        "as many tasks as there are workers, 16 to 10000 each)."),
    retries: int = typer.Option(1, min=0, help=RETRIES_HELP),
) -> None:
    """Reproduce the paper's simulation study (Table II, Fig. 12) with batched solves.

    Writes OUT/trials.csv, OUT/table.md, OUT/convergence.png and OUT/summary.json. With
    --ray the grid is solved in tasks (cells x trial batches of one method) on Ray, with the
    same trials.csv (docs/scaling.md).
    """
    cfg_kwargs: dict[str, Any] = dict(
        trials=trials,
        seed=seed,
        params=split_option("params", params, ("F", "S", "O")),
        models=split_option("models", models, ("inv", "semi")),
        angles=split_option("angles", angles, None, float),
        noise=split_option("noise", noise, ("L", "M", "H")),
        max_iters=max_iters,
    )
    if optimizer not in ("lm", "dogleg"):
        fail(f"--optimizer: expected lm or dogleg, got {optimizer!r}")
    cfg_kwargs["optimizer"] = optimizer
    if optimize not in ("auto", "yes", "no"):
        fail(f"--optimize: expected auto, yes or no, got {optimize!r}")
    cfg_kwargs["optimize"] = {"auto": None, "yes": True, "no": False}[optimize]
    cfg_kwargs["protocol"] = _protocol(protocol, focal, distance, pattern, elevation, views)
    if any(not 0 < a <= 360 for a in cfg_kwargs["angles"]):
        fail("--angles: each viewing range must be in (0, 360] degrees")
    if out.exists() and not out.is_dir():
        fail(f"--out: {out} exists and is not a folder")
    check_output(out)
    ray = ray or ray_address is not None
    if trials_per_task is not None and not ray:
        fail("--trials-per-task: the grid is split into tasks only with --ray")
    engine = open_engine(ray, ray_address, workers, retries) if ray else None

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..experiments import StudyConfig, run_study, write_outputs

    cfg = StudyConfig(**cfg_kwargs)
    n_struct = len(cfg.models) * len(cfg.params)
    console.print(
        f"simulate: {len(cfg.cells)} cells x {cfg.trials} trials x {n_struct} methods "
        f"= {len(cfg.cells) * cfg.trials * n_struct} solves"
        + ("" if engine is None else f" on Ray ({engine.workers} CPUs)")
    )
    with Progress(
        TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(), console=console, transient=False,
    ) as bar:  # fmt: skip
        task = bar.add_task("scenes", total=n_struct + 1)

        said = [0.0]

        def progress(stage: str, done: int, total: int) -> None:
            bar.update(task, completed=done, total=total, description=f"solved {stage}" if done > 1 else stage)
            # without a terminal the bar is not drawn: a line at most every 30 s instead
            if not console.is_terminal and (time.monotonic() - said[0] >= 30 or done == total):
                said[0] = time.monotonic()
                console.print(f"simulate: {done}/{total} ({'solved ' if done > 1 else ''}{stage})")

        if engine is None:
            try:
                result = run_study(cfg, progress)
            except RuntimeError as e:
                fail(f"simulate: {e}")
        else:
            try:
                result = run_study(cfg, progress, engine=engine, trials_per_task=trials_per_task)
            except RuntimeError as e:
                fail(f"simulate: {e}")
            finally:
                engine.close()
    try:
        summary = write_outputs(result, out)
    except OSError as e:
        fail(f"--out: cannot write {out}: {e.strerror or e}")
    t = summary["timings"]
    console.print((out / "table.md").read_text())
    console.print(
        f"wall {t['wall']:.2f} s, {t['us_per_problem_iteration']:.1f} µs per problem-iteration; "
        f"wrote {out}/trials.csv, table.md, convergence.png, summary.json"
    )
