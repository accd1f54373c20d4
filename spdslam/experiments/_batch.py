"""Many sequence runs at once: a manifest of (sequence, method, settings) jobs, run by an
engine (here or on Ray), each written as ``spdslam run`` writes it.

Manifest (YAML; paths relative to the manifest's folder)::

    defaults:                 # optional: settings every job starts from
      max_iterations: 100
    jobs:
      - sequence: data/room0
        methods: [quadric-slam, multi-rts, multi-spd]   # one job per method
      - sequence: data/room1
        method: multi-spd
        name: room1-online    # the output folder; default <sequence folder>-<method>
        online: {window: 30, every: 10}
        sigma: {inverse_box: 3}

A job's keys: ``sequence`` (required), ``method`` or ``methods``, ``name`` and the
settings of :data:`JOB_SETTINGS` (those of ``spdslam run``). Every error names the
manifest's line.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ..mapping import SETTINGS, RunSettings, SettingsError

__all__ = ["BATCH_COLUMNS", "JOB_SETTINGS", "Job", "JobReport", "map_sequence",
           "read_manifest", "run_batch", "write_batch_report"]

#: The settings a job may set, with what each means: the fields of ``mapping.RunSettings``
#: (the method aside), every ``Method`` field as an override (``spdslam run``'s options for
#: ``mapping.SETTINGS.overrides``; a method switch a new factor adds is a key here unchanged) and
#: ``overlay`` (``write_run``'s); ``spdslam run``'s options have the same names.
JOB_SETTINGS = {
    **{name: SETTINGS.help(name) for name in SETTINGS.run_names if name != "method"},
    **{name: f"override the method's {name} (mapping.Method)" for name in SETTINGS.method_fields},
    **SETTINGS.overrides,
    "overlay": "write overlay/ frames when the sequence has images (true or false)",
}
#: The synthetic room an online run with ``warmup`` replays first (``OnlineMapper.warmup``):
#: frames and objects, seen with the sequence's camera.
WARMUP_ROOM = (300, 40)


@dataclass(frozen=True)
class Job:
    """One run: ``sequence`` mapped with ``settings`` (its method named ``method``), written
    to the folder ``name`` (with overlay/ frames when ``overlay``); ``line``: its manifest
    line."""

    name: str
    sequence: Path
    method: str
    settings: RunSettings = field(default_factory=RunSettings)
    overlay: bool = True
    line: int | None = None


@dataclass
class JobReport:
    """What became of a job: ``status`` "done" or "failed"; when failed, ``stage`` ("read",
    "map" or "write") and ``error`` (one line); the metrics summary when it has ground truth."""

    job: Job
    status: str
    stage: str = ""
    error: str = ""
    attempts: int = 0
    seconds: float = 0.0
    where: str = ""
    objects: int | None = None
    metrics: dict = field(default_factory=dict)

    def row(self) -> dict:
        s = self.metrics.get("summary") or {}
        ate = (self.metrics.get("ate") or {}).get("optimized") or {}
        return {"job": self.job.name, "sequence": str(self.job.sequence), "method": self.job.method,
                "status": self.status, "stage": self.stage, "attempts": self.attempts,
                "seconds": round(self.seconds, 3), "worker": self.where, "objects": self.objects,
                "mean_iou": s.get("mean_iou"), "mean_orientation_deg": s.get("mean_orientation_deg"),
                "ate_rmse_m": ate.get("rmse"), "error": self.error}


# --- the manifest -------------------------------------------------------------------------
def _plain(name, node):
    """A YAML node as plain values: a scalar, a list or a mapping of them."""
    import yaml

    from ..io import yaml_mapping, yaml_scalar

    if isinstance(node, yaml.MappingNode):
        return {k: _plain(name, v) for k, _, v in yaml_mapping(name, node, "a mapping")}
    if isinstance(node, yaml.SequenceNode):
        return [_plain(name, i) for i in node.value]
    return yaml_scalar(node)


def _settings(name, pairs, where: str) -> dict:
    """{key: (value, key node, value node)} of a job's or ``defaults``' settings (keys of
    :data:`JOB_SETTINGS`); the values are checked by ``RunSettings`` (``_job``)."""
    from ..io import SequenceFormatError, yaml_line

    out = {}
    for key, knode, v in pairs:
        if key not in JOB_SETTINGS:
            raise SequenceFormatError(
                name, yaml_line(knode), f"a key of {where} among {', '.join(JOB_SETTINGS)}", repr(key))
        out[key] = (_plain(name, v), knode, v)
    return out


def _job(name, method: str, settings: dict, node) -> tuple[RunSettings, bool]:
    """(``RunSettings``, overlay) of a job's ``settings`` (``_settings``), or
    ``SequenceFormatError`` at the line of the setting that is wrong (the job's line when
    it came from a combination)."""
    import yaml

    from ..io import SequenceFormatError, yaml_line

    values = {k: v for k, (v, _, _) in settings.items() if k != "overlay"}
    overlay = settings.get("overlay", (True,))[0]
    if not isinstance(overlay, bool):
        raise SequenceFormatError(name, yaml_line(settings["overlay"][2]), "overlay: true or false",
                                  repr(overlay))
    try:
        return RunSettings.of(method, **values), overlay
    except SettingsError as e:
        key, _, sub = e.field.partition(".")
        where = node
        if key in settings:
            where = settings[key][2]
            if sub and isinstance(where, yaml.MappingNode):
                where = next((vn for kn, vn in where.value if kn.value == sub), where)
        expected, sep, got = e.reason.rpartition(", got ")
        raise SequenceFormatError(name, yaml_line(where), f"{e.field}: {expected if sep else e.reason}",
                                  got if sep else "a combination the settings refuse") from None


def read_manifest(path) -> list[Job]:
    """The jobs of a manifest, in order (``methods`` expanded), or ``SequenceFormatError``
    naming the file and line: unknown keys and settings, a missing sequence, duplicate job
    names, an online job with keyframes or estimated support planes."""
    import yaml

    from ..io import SequenceFormatError, yaml_kind, yaml_line, yaml_mapping, yaml_root, yaml_scalar
    from ..mapping import METHODS

    path = Path(path)
    name = str(path)
    root = yaml_root(path, name)
    defaults, jobs_node = {}, None
    for key, knode, v in yaml_mapping(name, root, "the manifest"):
        if key == "defaults":
            pairs = yaml_mapping(name, v, "defaults")
            for k, kn, _ in pairs:
                if k in ("sequence", "name"):
                    raise SequenceFormatError(name, yaml_line(kn), "defaults without sequence or name", repr(k))
            method_pairs = [p for p in pairs if p[0] in ("method", "methods")]
            defaults = {"_methods": _methods(name, method_pairs, METHODS)} if method_pairs else {}
            defaults.update(_settings(name, [p for p in pairs if p[0] not in ("method", "methods")], "defaults"))
        elif key == "jobs":
            jobs_node = v
        else:
            raise SequenceFormatError(name, yaml_line(knode), "a key of the manifest among defaults, jobs", repr(key))
    if jobs_node is None:
        raise SequenceFormatError(name, None, "a list of jobs (jobs:)", "none")
    if not isinstance(jobs_node, yaml.SequenceNode) or not jobs_node.value:
        raise SequenceFormatError(name, yaml_line(jobs_node), "a non-empty list of jobs", yaml_kind(jobs_node))
    jobs: list[Job] = []
    names: dict[str, int | None] = {}
    for node in jobs_node.value:
        pairs = yaml_mapping(name, node, "a job")
        seq = next((p for p in pairs if p[0] == "sequence"), None)
        if seq is None:
            raise SequenceFormatError(name, yaml_line(node), "a sequence for the job", "none")
        seq_value = yaml_scalar(seq[2])
        if not isinstance(seq_value, str) or not seq_value.strip():
            raise SequenceFormatError(name, yaml_line(seq[2]), "a sequence folder (a path)", yaml_kind(seq[2]))
        method_pairs = [p for p in pairs if p[0] in ("method", "methods")]
        methods = _methods(name, method_pairs, METHODS) if method_pairs else \
            defaults.get("_methods", ["multi-spd"])
        given = next((p for p in pairs if p[0] == "name"), None)
        if given is not None and len(methods) > 1:
            raise SequenceFormatError(name, yaml_line(given[1]), "no name for a job of several methods "
                                      "(each is named <name>-<method>)", repr(yaml_scalar(given[2])))
        settings = {k: v for k, v in defaults.items() if k != "_methods"}
        settings.update(_settings(name, [p for p in pairs if p[0] not in
                                         ("sequence", "method", "methods", "name")], "a job"))
        folder = Path(seq_value).expanduser()
        folder = folder if folder.is_absolute() else path.parent / folder
        for m in methods:
            job_name = yaml_scalar(given[2]) if given is not None else f"{folder.name}-{m}"
            if not isinstance(job_name, str) or not job_name or "/" in job_name or "\\" in job_name \
                    or job_name in (".", "..") or job_name.startswith("."):
                raise SequenceFormatError(name, yaml_line(given[2] if given is not None else node),
                                          "a job name that is a plain folder name", repr(job_name))
            if job_name in names:
                raise SequenceFormatError(name, yaml_line(node), f"unique job names ({job_name!r} is the job "
                                          f"of line {names[job_name]})", f"{job_name!r} twice")
            names[job_name] = yaml_line(node)
            run, overlay = _job(name, m, settings, node)
            jobs.append(Job(job_name, folder, m, run, overlay, yaml_line(node)))
    return jobs


def _methods(name, pairs, allowed) -> list[str]:
    import yaml

    from ..io import SequenceFormatError, yaml_line, yaml_scalar

    if len(pairs) > 1:
        raise SequenceFormatError(name, yaml_line(pairs[1][1]), "method or methods, not both", "both")
    key, _, v = pairs[0]
    items = v.value if key == "methods" and isinstance(v, yaml.SequenceNode) else [v]
    if key == "methods" and not isinstance(v, yaml.SequenceNode):
        raise SequenceFormatError(name, yaml_line(v), "methods: a list of methods", repr(yaml_scalar(v)))
    out = []
    for i in items:
        m = yaml_scalar(i)
        if m not in allowed:
            raise SequenceFormatError(name, yaml_line(i), f"a method among {', '.join(allowed)}", repr(m))
        if m in out:
            raise SequenceFormatError(name, yaml_line(i), "each method once", f"{m!r} twice")
        out.append(m)
    if not out:
        raise SequenceFormatError(name, yaml_line(v), "at least one method", "an empty list")
    return out


# --- running ------------------------------------------------------------------------------
def map_sequence(seq, settings: RunSettings, progress=None):
    """Map a sequence as ``spdslam run`` does: (``MapResult``, the online run's
    ``FrameRecord`` s or None): one batch optimisation (``mapping.run_sequence``), or, with
    ``settings.online``, a replay through the online mapper (``mapping.run_online``; with
    ``online.warmup`` a ``WARMUP_ROOM`` replayed first). An automatic association's scores
    are made here (``association_record``), where the run is, so that a worker hands back
    the record, not the sequence its tracks group."""
    import dataclasses

    from ..mapping import run_online, run_sequence
    from ._run_folder import association_record

    if settings.online is None:
        result = run_sequence(seq, settings, progress=progress)
        return dataclasses.replace(result, association=association_record(result), associated=()), None
    warmup = None
    if settings.online.warmup:
        from ..synthetic import make_room_sequence

        warmup = make_room_sequence(0, *WARMUP_ROOM, camera=seq.camera, truncation=True)
    return run_online(seq, settings, progress=progress, warmup=warmup)


def _map_task(job: Job, seq):
    """One job's mapping (runs in a worker): (MapResult, FrameRecords or None)."""
    return map_sequence(seq, job.settings)


def _read(job: Job):
    from ..io import read_sequence

    return read_sequence(job.sequence)


def run_batch(jobs: list[Job], out, engine=None, overwrite: bool = False,
              progress: Callable[[JobReport, int, int], None] | None = None) -> list[JobReport]:
    """Run the jobs on ``engine`` (default: this process, one after another) and write each
    into ``out/<job name>`` as ``spdslam run`` writes it (here, atomically: a failed job
    leaves no folder). A job whose sequence cannot be read, whose mapping raises in every
    attempt or whose outputs cannot be written is reported failed with its error; the
    others are unaffected. ``progress(report, done, total)`` as each job ends."""
    from ._engines import LocalEngine, error_line
    from ._run_folder import write_run

    engine = engine or LocalEngine()
    out = Path(out)
    reports: dict[int, JobReport] = {}
    tasks, owners = [], []
    done = 0
    for i, job in enumerate(jobs):
        t0 = time.perf_counter()
        try:
            seq = _read(job)
        except (ValueError, OSError) as e:
            reports[i] = JobReport(job, "failed", "read", error_line(e), 0, time.perf_counter() - t0)
            done += 1
            if progress:
                progress(reports[i], done, len(jobs))
            continue
        tasks.append((job, seq))
        owners.append(i)

    def write(o) -> None:  # as each job's mapping ends, its outputs are written
        nonlocal done
        i = owners[o.index]
        job, seq = tasks[o.index]
        if not o.ok:
            reports[i] = JobReport(job, "failed", "map", o.error, o.attempts, o.seconds, o.where)
        else:
            result, records = o.value
            try:
                metrics = write_run(out / job.name, seq, result, records, overlay=job.overlay,
                                    overwrite=overwrite, source=job.sequence)
                reports[i] = JobReport(job, "done", "", "", o.attempts, o.seconds, o.where,
                                       len(result.objects), metrics)
            except Exception as e:  # noqa: BLE001 - a full disk, a folder made meanwhile, …
                reports[i] = JobReport(job, "failed", "write", error_line(e), o.attempts, o.seconds, o.where)
        done += 1
        if progress:
            progress(reports[i], done, len(jobs))

    engine.map(_map_task, tasks, on_outcome=write)
    return [reports[i] for i in range(len(jobs))]


BATCH_COLUMNS = ["job", "sequence", "method", "status", "stage", "attempts", "seconds", "worker",
                 "objects", "mean_iou", "mean_orientation_deg", "ate_rmse_m", "error"]


def write_batch_report(out, reports: list[JobReport], engine: dict | None = None) -> None:
    """``out/batch.csv`` (a row per job, :data:`BATCH_COLUMNS`) and ``out/batch.json`` (the
    same rows and the engine), each written under a temporary name first."""
    import csv
    import io

    from ..evaluation import dumps_strict

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [r.row() for r in reports]
    buf = io.StringIO()
    w = csv.DictWriter(buf, BATCH_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    for fname, text in (("batch.csv", buf.getvalue()),
                        ("batch.json", dumps_strict({"engine": engine or {}, "jobs": rows}))):
        tmp = out / f".{fname}.tmp"
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(out / fname)
