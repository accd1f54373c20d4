"""The one home of a run's outputs: ``spdslam run``, a manifest's job and the Python API
write a run's folder through :func:`write_run`.

    OUT/map.json          the map (``io.write_map``; schema ``io.map_document``), with an
                          automatic association's scores against the instance ids, where
                          the detections carry them (``association_record``)
    OUT/trajectory.txt    the optimised poses (TUM)
    OUT/metrics.json      with ground truth: ``evaluation.evaluate_run``
    OUT/report.md         with ground truth: ``evaluation.report_markdown``
    OUT/map_top.png       the objects and trajectories from above
    OUT/overlay/          with images: the projected ellipsoids on the frames
    OUT/latency.csv/.png  an online run: the time of every frame

The folder appears whole or not at all (``io.write_folder_atomically``). A rerun recording
(a .rrd file anywhere, ``spdslam run --rerun`` and ``spdslam view``) is
``experiments.write_recording``'s, from the folder's map and trajectory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluation import association_scores, evaluate_run, ground_truth_in_map_frame, report_markdown
from ..io import dumps_strict, tum_text, write_folder_atomically, write_map
from ._figures import latency_csv, plot_latency, plot_map_top, write_overlays

__all__ = ["association_record", "frame_rate", "write_run"]


def frame_rate(seq) -> float | None:
    """The frame rate of ``seq`` (Hz) from the median step of its timestamps; None when
    they give none."""
    dt = np.diff(np.asarray(seq.timestamps, float))
    return 1.0 / float(np.median(dt)) if dt.size and np.median(dt) > 0 else None


def association_record(result) -> dict:
    """The run's ``association`` record, with ``evaluation.association_scores`` of an
    automatic association (``MapResult.associated``) whose detections all carry instance
    ids (without its track → instance ``mapping``)."""
    record = dict(result.association)
    if result.associated:
        tracks, seq = result.associated
        if seq.detections and all(d.instance is not None for d in seq.detections):
            scores = dict(association_scores(tracks, seq))
            scores.pop("mapping", None)
            record.update(scores)
    return record


def write_run(out, seq, result, records=None, *, overlay: bool = True,
              max_overlays: int | None = 60, overwrite: bool = False, source=None,
              up=None, extra: dict | None = None) -> dict:
    """Write the run ``result`` (a ``mapping.MapResult``) of ``seq`` into the folder ``out``
    (module docstring), atomically, and return its metrics (``evaluation.evaluate_run``).
    ``records``: an online run's ``FrameRecord`` s (latency.csv and latency.png);
    ``source``: the sequence folder it was read from, recorded (absolute) as map.json's
    ``sequence`` so that ``spdslam view OUT`` finds it. ``up``: the gravity direction of the
    result's frame for map_top.png (default the sequence's); ``extra``: {file name: text}
    written beside (``spdslam localize``'s localization.json)."""

    def write(tmp: Path) -> dict:
        m = result.as_dict()
        m["association"] = association_record(result)
        if source is not None:
            m["sequence"] = str(Path(source).resolve())
        metrics = evaluate_run(m, result.objects, result.initial_objects, result.poses_tum, seq)
        if "to_groundtruth" in metrics:
            m["to_groundtruth"] = metrics["to_groundtruth"]
        write_map(tmp / "map.json", m)
        (tmp / "trajectory.txt").write_text(tum_text(result.poses_tum), encoding="utf-8")
        if "summary" in metrics or "ate" in metrics:
            (tmp / "metrics.json").write_text(dumps_strict(metrics) + "\n", encoding="utf-8")
            (tmp / "report.md").write_text(report_markdown(metrics, m), encoding="utf-8")
        for name, text in (extra or {}).items():
            (tmp / name).write_text(text, encoding="utf-8")
        gravity = up
        if gravity is None:
            gravity = (0, 0, 1) if seq.priors is None or seq.priors.up is None else seq.priors.up
        T = np.asarray(metrics["to_groundtruth"]) if "to_groundtruth" in metrics else None
        gt_cuboids, gt_traj = ground_truth_in_map_frame(seq, T)
        labels = [f"{o.label} {o.id}" for o in result.objects]
        closure = (getattr(result, "trajectory", None) or {}).get("loop_closure") or {}
        loops = [(*lp["frames"], lp["status"] == "verified") for lp in closure.get("loops", [])
                 if lp["status"] in ("verified", "rejected")]
        plot_map_top(
            tmp / "map_top.png", [o.ellipsoid for o in result.objects], labels=labels,
            gt_cuboids=gt_cuboids, trajectory=result.poses_tum, gt_trajectory=gt_traj, up=gravity,
            title=f"{result.method.name} on {seq.name}", loops=loops,
        )
        if overlay and seq.images:
            write_overlays(tmp / "overlay", seq, [o.ellipsoid for o in result.objects],
                           result.poses_tum, max_frames=max_overlays, labels=labels)
        if records is not None:
            (tmp / "latency.csv").write_text(latency_csv(records), encoding="utf-8")
            plot_latency(tmp / "latency.png", records, rate=frame_rate(seq),
                         title=f"online mapping of {seq.name}")
        return metrics

    return write_folder_atomically(out, write, overwrite)
