"""``compare`` and ``batch``: several runs of a study (methods side by side, or a manifest's
jobs), each job's failure reported and the others kept."""

from __future__ import annotations

from pathlib import Path

import typer

from ._app import (
    RAY_ADDRESS_HELP,
    RAY_HELP,
    RETRIES_HELP,
    WORKERS_HELP,
    app,
    check_output,
    console,
    fail,
    open_engine,
)
from ._common import (
    check_out,
    load_sequence,
    run_settings,
    sequence_path,
)
from ._simulate import split_option

__all__ = ["compare", "batch"]


def _say_job(report, done: int, total: int) -> None:
    """One line per finished job: stdout when done, stderr when failed."""
    from ..evaluation import shown

    j = report.job
    if report.status == "done":
        s = report.metrics.get("summary") or {}
        iou = f", mean IoU {shown(s['mean_iou'])}" if s else ""
        console.print(f"[{done}/{total}] {j.name}: {report.objects} objects{iou} "
                      f"({report.seconds:.1f} s{', ' + report.where if report.where != 'local' else ''})",
                      highlight=False, markup=False)
    else:
        tries = f", {report.attempts} attempts" if report.attempts > 1 else ""
        # plain, so that the error stays on one line whatever the terminal's width
        typer.echo(f"[{done}/{total}] {j.name} failed ({report.stage}{tries}): {report.error}", err=True)


def _run_jobs(jobs, out, ray, ray_address, workers, retries, overwrite):
    """The jobs run (``experiments.run_batch``) with a line per job, batch.csv and
    batch.json written: the reports."""
    from ..experiments import run_batch, write_batch_report

    for job in jobs:
        check_out(out / job.name, overwrite)
    engine = open_engine(ray, ray_address, workers, retries)
    console.print(f"{len(jobs)} jobs on {engine.name}"
                  + (f" ({engine.workers} CPUs)" if engine.name == "ray" else ""))
    try:
        reports = run_batch(jobs, out, engine, overwrite=overwrite, progress=_say_job)
    finally:
        engine.close()
    try:
        write_batch_report(out, reports, {"name": engine.name, "workers": engine.workers,
                                          "retries": retries})
    except OSError as e:
        fail(f"--out: cannot write {out}: {e.strerror or e}")
    return reports


@app.command()
def compare(
    sequence: Path = typer.Argument(..., help="Sequence folder with object ground truth."),
    out: Path = typer.Option(Path("compare"), "--out", help="Output folder (one sub-folder per method)."),
    methods: str = typer.Option("quadric-slam,multi-rts,multi-spd", help="Methods to run."),
    overwrite: bool = typer.Option(False, help="Replace non-empty outputs."),
    ray: bool = typer.Option(False, "--ray", help=RAY_HELP),
    ray_address: str | None = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP),
    workers: int | None = typer.Option(None, min=1, help=WORKERS_HELP),
    retries: int = typer.Option(1, min=0, help=RETRIES_HELP),
) -> None:
    """Run several methods on one sequence and write a Table-III-like OUT/table.md (and
    OUT/batch.csv, a line per method run)."""
    from ..evaluation import FRONT_END_NAMES, table_iii
    from ..experiments import Job
    from ..mapping import METHODS

    names = split_option("methods", methods, tuple(METHODS))
    sequence_path(sequence)
    check_output(out, [sequence])
    seq = load_sequence(sequence)
    if not seq.objects_gt:
        fail(f"{sequence}: expected object ground truth (objects_gt.txt) to compare methods, got none")
    check_out(out, overwrite)
    jobs = [Job(name, sequence, name, run_settings(name), overlay=False) for name in names]
    reports = _run_jobs(jobs, out, ray, ray_address, workers, retries, overwrite)
    failed = [r for r in reports if r.status != "done"]
    if failed:
        fail(f"{len(failed)} of {len(reports)} methods failed (first: {failed[0].job.name}: "
             f"{failed[0].error}); see {out / 'batch.csv'}", code=1)
    rows, fronts = [], {}
    for r in reports:
        init = METHODS[r.job.method].initialization
        if init not in fronts:
            fronts[init] = r.metrics["front_end"]["summary"]
        rows.append(("back end", r.job.method, r.metrics["summary"]))
    front_rows = [("front end", FRONT_END_NAMES[k], v) for k, v in fronts.items()]
    table = f"# {seq.name}\n\n" + table_iii(front_rows + rows)
    (out / "table.md").write_text(table, encoding="utf-8")
    console.print(table)


@app.command()
def batch(
    manifest: Path = typer.Argument(..., help="The manifest (YAML): jobs of sequence, method and settings "
        "(docs/scaling.md)."),
    out: Path = typer.Option(Path("batch"), "--out", help="Output folder: a sub-folder per job, batch.csv and "
        "batch.json."),
    overwrite: bool = typer.Option(False, help="Replace non-empty job folders."),
    ray: bool = typer.Option(False, "--ray", help=RAY_HELP),
    ray_address: str | None = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP),
    workers: int | None = typer.Option(None, min=1, help=WORKERS_HELP),
    retries: int = typer.Option(1, min=0, help=RETRIES_HELP),
) -> None:
    """Run many (sequence, method, settings) jobs of a manifest, each written to OUT/NAME as
    spdslam run writes it; OUT/batch.csv and OUT/batch.json say how each ended. A job that
    fails is reported and the others finish; the exit status is then 1."""
    from ..experiments import read_manifest
    from ..io import SequenceFormatError

    try:
        jobs = read_manifest(manifest)
    except SequenceFormatError as e:
        fail(str(e))
    check_output(out, [manifest] + [j.sequence for j in jobs])
    reports = _run_jobs(jobs, out, ray, ray_address, workers, retries, overwrite)
    failed = [r for r in reports if r.status != "done"]
    console.print(f"{len(reports) - len(failed)} of {len(reports)} jobs done; wrote {out / 'batch.csv'}")
    if failed:
        raise typer.Exit(1)
