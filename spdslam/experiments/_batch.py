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

import numpy as np

__all__ = ["BATCH_COLUMNS", "JOB_SETTINGS", "Job", "JobReport", "latency_writer", "map_sequence",
           "read_manifest", "run_batch", "write_batch_report"]

#: The settings a job may set (``spdslam run``'s options), with what each expects.
JOB_SETTINGS = {
    "max_iterations": "a positive integer (LM iterations per stage)",
    "associate": "instances or auto",
    "keyframes": "all, motion or a positive integer",
    "support_planes": "priors, estimate or optimized",
    "sigma": "a mapping NAME: VALUE",
    "parameterization": "a parameterisation",
    "box_model": "a box model",
    "object_shape": "a silhouette model",
    "truncation_margin": "a number of pixels",
    "robust": "a list of KERNEL or TYPE=KERNEL[:K]",
    "robust_k": "a positive number",
    "class_table": "true or false",
    "overlay": "true or false",
    "online": "false, true or a mapping window/every/iterations/final_batch/warmup",
}
#: ``online``'s keys and defaults (``spdslam run --online``'s).
ONLINE_DEFAULTS = {"window": 30, "every": 10, "iterations": 5, "final_batch": True, "warmup": False}
#: The synthetic room an online run with ``warmup`` replays first (``OnlineMapper.warmup``):
#: frames and objects, seen with the sequence's camera.
WARMUP_ROOM = (300, 40)


@dataclass(frozen=True)
class Job:
    """One run: ``sequence`` mapped by ``method`` with ``settings`` (keys of
    :data:`JOB_SETTINGS`), written to the folder ``name``; ``line``: its manifest line."""

    name: str
    sequence: Path
    method: str
    settings: dict = field(default_factory=dict)
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
def _settings(name, pairs, where: str) -> dict:
    """The settings of a job or of ``defaults`` from (key, key node, value node) pairs, checked."""
    import yaml

    from ..io import SequenceFormatError, yaml_kind, yaml_line, yaml_mapping, yaml_number, yaml_scalar
    from ..mapping import (ASSOCIATIONS, BOX_MODELS, DEFAULT_MAPPING_SIGMAS, OBJECT_SHAPE_CHOICES,
                           PARAMETERIZATIONS, SUPPORT_PLANES, check_sigma, parse_keyframes,
                           parse_robust)

    def err(node, expected, got=None):
        raise SequenceFormatError(name, yaml_line(node), expected, yaml_kind(node) if got is None else got)

    def choice(node, allowed, what):
        v = yaml_scalar(node)
        if v not in allowed:
            err(node, f"{what}: one of {', '.join(allowed)}")
        return v

    def boolean(node, what):
        v = yaml_scalar(node)
        if not isinstance(v, bool):
            err(node, f"{what}: true or false")
        return v

    def positive_int(node, what, least=1):
        v = yaml_scalar(node)
        if isinstance(v, bool) or not isinstance(v, int) or v < least:
            err(node, f"{what}: an integer ≥ {least}")
        return v

    out, robust_node = {}, None
    for key, knode, v in pairs:
        if key == "max_iterations":
            out[key] = positive_int(v, key)
        elif key == "associate":
            out[key] = choice(v, ASSOCIATIONS, key)
        elif key == "keyframes":
            try:
                out[key] = parse_keyframes(yaml_scalar(v))
            except ValueError:
                err(v, "keyframes: all, motion or a positive integer")
        elif key == "support_planes":
            out[key] = choice(v, SUPPORT_PLANES, key)
        elif key == "parameterization":
            out[key] = choice(v, PARAMETERIZATIONS, key)
        elif key == "box_model":
            out[key] = choice(v, BOX_MODELS, key)
        elif key == "object_shape":
            out[key] = choice(v, OBJECT_SHAPE_CHOICES, key)
        elif key == "truncation_margin":
            out[key] = yaml_number(name, v, key)
        elif key == "robust_k":
            k = yaml_number(name, v, key)
            if not k > 0:
                err(v, "robust_k: a positive number", repr(k))
            out[key] = k
        elif key == "robust":
            items = [v] if isinstance(v, yaml.ScalarNode) else v.value if isinstance(v, yaml.SequenceNode) else None
            if items is None or not all(isinstance(yaml_scalar(i), str) for i in items):
                err(v, "robust: a kernel or a list of KERNEL or TYPE=KERNEL[:K]")
            out[key] = [yaml_scalar(i) for i in items]
            robust_node = v
        elif key in ("class_table", "overlay"):
            out[key] = boolean(v, key)
        elif key == "sigma":
            sig = {}
            for sname, sk, sv in yaml_mapping(name, v, "sigma"):
                if sname not in DEFAULT_MAPPING_SIGMAS:
                    err(sk, f"a sigma among {', '.join(sorted(DEFAULT_MAPPING_SIGMAS))}", repr(sname))
                value = yaml_number(name, sv, f"sigma {sname}")
                try:
                    sig[sname] = check_sigma(sname, value)
                except ValueError:
                    err(sv, f"a positive sigma {sname}", repr(value))
            out[key] = sig
        elif key == "online":
            if isinstance(v, yaml.MappingNode):
                on = dict(ONLINE_DEFAULTS)
                for ok, okn, ov in yaml_mapping(name, v, "online"):
                    if ok in ("final_batch", "warmup"):
                        on[ok] = boolean(ov, f"online {ok}")
                    elif ok in ONLINE_DEFAULTS:
                        on[ok] = positive_int(ov, f"online {ok}", 2 if ok == "window" else 1)
                    else:
                        raise SequenceFormatError(name, yaml_line(okn), f"a key of online among {', '.join(ONLINE_DEFAULTS)}", repr(ok))
                out[key] = on
            else:
                out[key] = dict(ONLINE_DEFAULTS) if boolean(v, "online") else None
        else:
            raise SequenceFormatError(
                name, yaml_line(knode), f"a key of {where} among {', '.join(JOB_SETTINGS)}", repr(key))
    if robust_node is not None:
        try:
            parse_robust(out["robust"], out.get("robust_k"))
        except ValueError as e:
            err(robust_node, "robust: " + str(e).rsplit(", got", 1)[0], str(out["robust"]))
    return out


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
    jobs, names = [], {}
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
        if settings.get("online"):
            if settings.get("keyframes", "all") != "all":
                raise SequenceFormatError(name, yaml_line(node), "keyframes all for an online job", repr(settings["keyframes"]))
            if settings.get("support_planes", "priors") != "priors":
                raise SequenceFormatError(name, yaml_line(node), "support_planes priors for an online job",
                                          repr(settings["support_planes"]))
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
            jobs.append(Job(job_name, folder, m, dict(settings), yaml_line(node)))
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
def map_sequence(seq, method: str, *, online: dict | None = None, max_iterations: int = 100,
                 sigma: dict | None = None, associate: str | None = None,
                 keyframes: str | int = "all", support_planes: str = "priors", progress=None,
                 **overrides):
    """Map a sequence as ``spdslam run`` does: (``MapResult``, the online run's
    ``FrameRecord``s or None). ``online``: ``run_online``'s window, every, iterations
    (per optimisation), final_batch and warmup (a ``WARMUP_ROOM`` replayed first); without it one batch optimisation
    (``run_sequence``). The other keywords are ``Method`` overrides (None: the method's)."""
    from ..mapping import run_online, run_sequence

    overrides = {k: v for k, v in overrides.items() if v is not None}
    if online is None:
        return run_sequence(seq, method, sigmas=sigma or {}, max_iterations=max_iterations,
                            associate=associate, keyframes=keyframes,
                            support_planes=support_planes, progress=progress, **overrides), None
    on = {**ONLINE_DEFAULTS, **online}
    warmup = None
    if on["warmup"]:
        from ..synthetic import make_room_sequence

        warmup = make_room_sequence(0, *WARMUP_ROOM, camera=seq.camera, truncation=True)
    return run_online(seq, method, associate=associate, sigmas=sigma or {},
                      final_iterations=max_iterations, progress=progress, window=on["window"],
                      every=on["every"], max_iterations=on["iterations"],
                      final_batch=on["final_batch"], warmup=warmup, **overrides)


def latency_writer(seq, records):
    """(``extra``, ``rate``): ``write_run``'s ``extra``, which writes latency.csv and
    latency.png of an online run's ``records``, and the frame rate of ``seq`` (None when its
    timestamps give none)."""
    from ..evaluation import latency_csv, plot_latency

    dt = np.diff(np.asarray(seq.timestamps, float))
    rate = 1.0 / float(np.median(dt)) if dt.size and np.median(dt) > 0 else None

    def extra(folder):
        (folder / "latency.csv").write_text(latency_csv(records), encoding="utf-8")
        plot_latency(folder / "latency.png", records, rate=rate, title=f"online mapping of {seq.name}")

    return extra, rate


def _job_settings(job: Job) -> dict:
    """A job's settings as ``map_sequence``'s keywords."""
    from ..mapping import parse_robust

    kw = {k: v for k, v in job.settings.items()
          if k not in ("class_table", "overlay", "robust", "robust_k")}
    kw.update(parse_robust(job.settings.get("robust"), job.settings.get("robust_k")))
    return kw


def _map_task(job: Job, seq):
    """One job's mapping (runs in a worker): (MapResult, FrameRecords or None)."""
    return map_sequence(seq, job.method, **_job_settings(job))


def _read(job: Job):
    from ..io import read_sequence, without_class_table

    seq = read_sequence(job.sequence)
    return seq if job.settings.get("class_table", True) else without_class_table(seq)


def run_batch(jobs: list[Job], out, engine=None, overwrite: bool = False,
              progress: Callable[[JobReport, int, int], None] | None = None) -> list[JobReport]:
    """Run the jobs on ``engine`` (default: this process, one after another) and write each
    into ``out/<job name>`` as ``spdslam run`` writes it (here, atomically: a failed job
    leaves no folder). A job whose sequence cannot be read, whose mapping raises in every
    attempt or whose outputs cannot be written is reported failed with its error; the
    others are unaffected. ``progress(report, done, total)`` as each job ends."""
    from ..evaluation import write_run
    from ._engines import LocalEngine, error_line

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
            extra = latency_writer(seq, records)[0] if records is not None else None
            try:
                metrics = write_run(out / job.name, seq, result, overlay=job.settings.get("overlay", True),
                                    overwrite=overwrite, source=job.sequence, extra=extra)
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
