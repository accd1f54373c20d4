"""Online mapping (``spdslam.mapping.OnlineMapper``): time per frame, on real data and on a
long synthetic room, against the batch map.

1. fr2_desk (``../shared/data/tum_fr2_desk``, skipped when absent): the batch run
   (``run_sequence``), then the sequence replayed frame by frame through the online mapper,
   twice in one process (the first replay compiles; the second runs on compiled code, as a
   long-running mapper or a warm compilation cache does). Per replay: median, 99th
   percentile and maximum time per frame; the frames processed; the delay of the last frame
   and the largest delay when frames arrive at the sequence's own rate (30 Hz) and wait in
   a queue while the mapper is busy (computed from the measured times: frame i arrives at
   tᵢ − t₀, starts when it has arrived and frame i−1 is done); the mean IoU of the online
   map, without and with the final batch optimisation, against the batch map's.
2. The demo rooms (``--seeds``): the final batch optimisation's cost against the batch
   run's, and the mean IoU of the online map (``demo_rooms``).
3. A demo room of ``--room-frames`` frames (``make_room_sequence``, ``--room-objects``
   objects, association by instance id), replayed twice as above: time per frame against
   the frames seen; the fitted exponent b of (mean time per frame over a block of frames) ∝
   (frames seen)^b over ``--blocks`` log-spaced blocks after the first ``--warmup`` frames
   (b ≈ 0: the cost per frame does not grow); after frame ``SETTLED`` (1 500) the slowest
   frames, how many exceed 100 and 300 ms, the growth of resident memory, and Python's
   garbage collector's full passes (generation 2: how many, the longest, in how many of the
   5 slowest frames one ran); ``--freeze-gc``: ``gc.collect(); gc.freeze()`` before each
   replay (docs/online.md, "Pauses of the garbage collector"); ``--room-background``: the
   optimisations in the mapper's worker (``background=True``), the frames added as fast as
   ``add_frame`` returns (its own time is what is timed; the worker runs one optimisation for
   all the frames that queued meanwhile) or, with ``--room-rate HZ``, each at its time at
   that rate. The first replay's blocks
   include the
   compilations, which happen when the problem outgrows its padded shapes (a one-off cost,
   not one that grows with the frames).

4. ``--live`` (fr2_desk): as a robot runs it. Each replay is a fresh process with a warm
   disk cache (filled by a first process that also runs the batch map) and no in-process
   warm-up, and the frames are added at the recording's own rate (``run_online(realtime=True)``):
   with the optimisations in the background (``online.background``) and, with
   ``--live-modes background,inline``, in line as well. Per replay: the time ``add_frame``
   took (median, 99th percentile, maximum, frames over a 30 Hz camera's 33 ms; ``--freeze-gc``:
   ``gc.freeze()`` once the recording is read, as ``spdslam run`` does) and the map's
   lag (seconds from a frame's arrival to the first published map that used it: median,
   maximum), and the mean IoU after the final batch against the batch map's.

    python3 benchmarks/online.py [--out benchmarks/results/online.json]
    python3 benchmarks/online.py --skip-fr2 --room-frames 2000
    python3 benchmarks/online.py --skip-fr2 --room-frames 30000 --seeds "" [--freeze-gc] [--room-background]
    python3 benchmarks/online.py --live --skip-fr2 --skip-room --seeds ""
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout

FR2 = HERE.parent / ".." / "shared" / "data" / "tum_fr2_desk"


def stats(records, timestamps) -> dict:
    """Figures of one replay (module docstring)."""
    sec = np.array([r.seconds for r in records])
    t = np.asarray(timestamps, float)
    arrive = t - t[0]
    done = 0.0
    delay = np.zeros(len(sec))
    for i, (a, s) in enumerate(zip(arrive, sec)):
        done = max(a, done) + s
        delay[i] = done - a
    return dict(frames=len(records), median_ms=1e3 * float(np.median(sec)),
                p99_ms=1e3 * float(np.percentile(sec, 99)), max_ms=1e3 * float(sec.max()),
                total_s=float(sec.sum()), rate_hz=float(1.0 / np.median(np.diff(t))),
                max_delay_s=float(delay.max()), last_delay_s=float(delay[-1]),
                frames_with_optimisation=int(sum(r.factors > 0 for r in records)))


def mean_iou(result, seq) -> float:
    from spdslam.evaluation import evaluate_run

    m = evaluate_run(result.as_dict(), result.objects, result.initial_objects, result.poses_tum, seq)
    return float(m["summary"]["mean_iou"])


def fr2(args) -> dict:
    from spdslam.io import read_sequence
    from spdslam.mapping import OnlineMapper, run_sequence

    seq = read_sequence(FR2)
    t0 = time.perf_counter()
    batch = run_sequence(seq, "multi-spd")
    out = {"batch": dict(seconds=time.perf_counter() - t0, objects=len(batch.objects),
                         mean_iou=mean_iou(batch, seq))}
    print(f"fr2_desk batch: {len(batch.objects)} objects, mean IoU {out['batch']['mean_iou']:.3f}, "
          f"{out['batch']['seconds']:.1f} s", flush=True)
    by_frame: dict = {}
    for d in seq.detections:
        by_frame.setdefault(d.frame, []).append(d)
    for rep in ("first", "second"):
        m = OnlineMapper(seq.camera, seq.priors, "multi-spd", associate="auto", window=args.window,
                         every=args.every, iterations=args.iterations)
        for i in range(len(seq)):
            m.add_frame(seq.timestamps[i], seq.poses_tum[i], detections=by_frame.get(i, ()))
        r = stats(m.records, seq.timestamps)
        online = m.finish(final_batch=False)
        final = m.finish(final_batch=True)
        r.update(objects_online=len(online.objects), mean_iou_online=mean_iou(online, seq),
                 objects_final=len(final.objects), mean_iou_final=mean_iou(final, seq))
        out[rep + "_replay"] = r
        print(f"fr2_desk replay ({rep}): {r['frames']} frames, per frame median {r['median_ms']:.3g} ms, "
              f"p99 {r['p99_ms']:.3g} ms, max {r['max_ms']:.3g} ms; at {r['rate_hz']:.3g} Hz the "
              f"largest delay {r['max_delay_s']:.3g} s, the last frame's {r['last_delay_s']:.3g} s; "
              f"mean IoU online {r['mean_iou_online']:.3f} ({r['objects_online']} objects), "
              f"after the final batch {r['mean_iou_final']:.3f} ({r['objects_final']})", flush=True)
    return out


def live_child(mode: str, out: Path, freeze_gc: bool = False) -> None:
    """One fresh process of ``--live`` (``mode``: warm, background or inline): figures to ``out``;
    ``freeze_gc``: ``gc.freeze()`` once the recording is read (as ``spdslam run``)."""
    from spdslam.io import read_sequence
    from spdslam.mapping import run_online, run_sequence

    seq = read_sequence(FR2)
    if freeze_gc and mode != "warm":
        gc.collect()
        gc.freeze()
    if mode == "warm":  # fill the disk cache for both paths, and the batch map's IoU
        batch = run_sequence(seq, "multi-spd")
        run_online(seq, "multi-spd")
        out.write_text(json.dumps({"batch_mean_iou": mean_iou(batch, seq)}))
        return
    t0 = time.perf_counter()
    result, records = run_online(seq, "multi-spd", realtime=True, background=mode == "background")
    sec = np.array([r.seconds for r in records])
    lag = np.array([r.lag for r in records])
    lag = lag[np.isfinite(lag)]
    out.write_text(json.dumps(dict(
        frames=len(records), wall_s=time.perf_counter() - t0, median_ms=1e3 * float(np.median(sec)),
        p99_ms=1e3 * float(np.percentile(sec, 99)), max_ms=1e3 * float(sec.max()),
        over_33ms=int((sec > 1 / 30).sum()), lag_median_s=float(np.median(lag)), lag_max_s=float(lag.max()),
        freeze_gc=freeze_gc,
        frames_with_lag=int(lag.size), mean_iou_final=mean_iou(result, seq), objects=len(result.objects))))


def live(args) -> dict:
    """``--live`` (module docstring): each replay in a fresh process."""
    import subprocess
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ["warm"] + args.live_modes:
            path = Path(tmp) / f"{mode}.json"
            subprocess.run([sys.executable, __file__, "--live-child", mode, "--live-out", str(path)]
                           + (["--freeze-gc"] if args.freeze_gc else []), check=True)
            out[mode] = json.loads(path.read_text())
            if mode == "warm":
                print(f"fr2_desk batch map: mean IoU {out[mode]['batch_mean_iou']:.3f}", flush=True)
                continue
            r = out[mode]
            print(f"fr2_desk live ({mode}, fresh process, warm disk cache, {r['frames']} frames at 30 Hz): "
                  f"add_frame median {r['median_ms']:.3g} ms, p99 {r['p99_ms']:.3g} ms, max {r['max_ms']:.4g} ms, "
                  f"{r['over_33ms']} frames over 33 ms; map lag median {r['lag_median_s']:.3g} s, "
                  f"max {r['lag_max_s']:.3g} s; mean IoU after the final batch {r['mean_iou_final']:.3f} "
                  f"({r['objects']} objects) against the batch map's {out['warm']['batch_mean_iou']:.3f}",
                  flush=True)
    return out


def demo_rooms(args) -> dict:
    """Per demo room (``make_room_sequence(seed)``, association by instance id): the batch
    map and the replay, both LM run to convergence (relative tolerance 1e-10): the relative
    difference of the final batch optimisation's cost from the batch run's, and the mean
    IoU of the batch map, the online map and the map after the final batch."""
    from spdslam.mapping import run_online, run_sequence
    from spdslam.solver import clear_caches
    from spdslam.synthetic import make_room_sequence

    out = {}
    for seed in args.seeds:
        seq = make_room_sequence(seed)
        # the demo rooms' boxes move their drifting poses (initial_poses input, as spdslam demo maps)
        batch = run_sequence(seq, "multi-spd", tolerance=1e-10, max_iterations=300, initial_poses="input")
        online, _ = run_online(seq, final_batch=False, window=args.window, every=args.every,
                               iterations=args.iterations, initial_poses="input")
        final, _ = run_online(seq, window=args.window, every=args.every, iterations=args.iterations,
                              max_iterations=300, tolerance=1e-10, initial_poses="input")
        r = dict(batch_cost=batch.final_cost, final_cost=final.final_cost,
                 cost_rel_diff=abs(final.final_cost - batch.final_cost) / batch.final_cost,
                 iou_batch=mean_iou(batch, seq), iou_online=mean_iou(online, seq),
                 iou_final=mean_iou(final, seq))
        out[f"seed_{seed}"] = r
        clear_caches()
        print(f"demo room {seed}: final batch cost {r['final_cost']:.8g} against the batch run's "
              f"{r['batch_cost']:.8g} (relative difference {r['cost_rel_diff']:.2g}); mean IoU batch "
              f"{r['iou_batch']:.3f}, online {r['iou_online']:.3f}, after the final batch "
              f"{r['iou_final']:.3f}", flush=True)
    return out


#: The frame after which a long stream has no excuse for a slow frame (issue 48: none over
#: 300 ms in line after it, memory growth ≤ 100 MB).
SETTLED = 1500


def rss_mb() -> float | None:
    """The process's resident memory now (MB), from /proc (None elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def room(args) -> dict:
    from spdslam.mapping import OnlineMapper
    from spdslam.synthetic import make_room_sequence

    seq = make_room_sequence(args.seed, args.room_frames, args.room_objects, drift=0.001)
    by_frame: dict = {}
    for d in seq.detections:
        by_frame.setdefault(d.frame, []).append(d)
    out = {}
    for rep in ("first", "second"):
        m = OnlineMapper(seq.camera, seq.priors, "multi-spd", associate="instances", window=args.window,
                         every=args.every, iterations=args.iterations, initial_poses="input",
                         background=args.room_background)
        if args.freeze_gc:  # docs/online.md: the objects alive now out of every full collection
            gc.collect()
            gc.freeze()
        collections: list = []  # the collector's full passes: (start, seconds)
        began: list = []

        def watch(phase, info):
            if info["generation"] == 2:
                if phase == "start":
                    began.append(time.perf_counter())
                else:
                    collections.append((began[-1], time.perf_counter() - began[-1]))

        gc.callbacks.append(watch)
        t0 = time.perf_counter()
        rss_settled = None
        starts = np.empty(len(seq))
        for i in range(len(seq)):
            if args.room_rate > 0:  # the frame arrives at its time
                time.sleep(max(0.0, t0 + i / args.room_rate - time.perf_counter()))
            starts[i] = time.perf_counter()
            m.add_frame(seq.timestamps[i], seq.poses_tum[i], detections=by_frame.get(i, ()))
            if i == SETTLED:
                rss_settled = rss_mb()
        m.wait()  # in the background: the worker's last optimisation
        wall = time.perf_counter() - t0
        rss_end = rss_mb()
        gc.callbacks.remove(watch)
        gc.unfreeze()
        sec = np.array([r.seconds for r in m.records])
        late = sec[SETTLED:]
        slowest = np.argsort(late)[::-1][:5] + SETTLED
        blocks = np.geomspace(max(args.warmup, 1), len(sec), args.blocks + 1).astype(int)
        mid, mean = [], []
        for a, b in zip(blocks[:-1], blocks[1:]):
            if b - a >= args.every:  # at least one optimisation in the block
                mid.append(np.sqrt(a * b))
                mean.append(sec[a:b].mean())
        b_exp, _ = np.polyfit(np.log(mid), np.log(mean), 1)
        r = dict(frames=len(seq), objects=args.room_objects, detections=len(seq.detections), freeze_gc=args.freeze_gc,
                 background=args.room_background, rate_hz=args.room_rate,
                 optimisations=int(sum(1 for x in m.records if x.factors)),
                 wall_s=wall, median_ms=1e3 * float(np.median(sec)), p99_ms=1e3 * float(np.percentile(sec, 99)),
                 exponent=float(b_exp), objects_mapped=len(m.landmarks),
                 max_ms_after_settled=1e3 * float(late.max()) if late.size else None,
                 over_300ms_after_settled=int((late > 0.3).sum()), over_100ms_after_settled=int((late > 0.1).sum()),
                 slowest_after_settled=[(int(k), 1e3 * float(sec[k])) for k in slowest],
                 full_collections=len(collections),
                 full_collection_max_ms=1e3 * max([d for _, d in collections] or [0.0]),
                 slowest_with_a_full_collection=int(sum(any(starts[k] <= t0_ <= starts[k] + sec[k]
                                                            for t0_, _ in collections) for k in slowest)),
                 rss_mb_settled=rss_settled, rss_mb_end=rss_end,
                 blocks=[dict(frames=float(x), mean_ms=1e3 * float(y)) for x, y in zip(mid, mean)])
        out[rep + "_replay"] = r
        print(f"room {len(seq)} frames x {args.room_objects} objects ({len(seq.detections)} boxes), "
              f"{rep} replay{' (optimisations in the background)' if args.room_background else ''}"
              f"{f', frames at {args.room_rate:g} Hz' if args.room_rate > 0 else ''}: {wall:.1f} s, "
              f"{r['optimisations']} optimisations, per frame median {r['median_ms']:.3g} ms, p99 {r['p99_ms']:.3g} ms; "
              f"fitted exponent of time per frame against frames seen (after {args.warmup}): "
              f"{r['exponent']:.3f}", flush=True)
        if late.size:
            grow = "–" if rss_settled is None or rss_end is None else f"{rss_end - rss_settled:+.0f} MB"
            print(f"  after frame {SETTLED}: max {r['max_ms_after_settled']:.4g} ms, "
                  f"{r['over_300ms_after_settled']} frames over 300 ms, {r['over_100ms_after_settled']} over 100 ms; "
                  f"slowest {', '.join(f'{k}: {v:.0f} ms' for k, v in r['slowest_after_settled'])}; "
                  f"resident memory {rss_settled} → {rss_end} MB ({grow}); the collector's full passes: "
                  f"{r['full_collections']}, at most {r['full_collection_max_ms']:.0f} ms, in "
                  f"{r['slowest_with_a_full_collection']} of the 5 slowest frames", flush=True)
        for blk in r["blocks"]:
            print(f"  around frame {blk['frames']:7.0f}: {blk['mean_ms']:.3g} ms per frame")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="Write the figures as JSON here.")
    ap.add_argument("--window", type=int, default=30)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--skip-fr2", action="store_true")
    ap.add_argument("--skip-room", action="store_true")
    ap.add_argument("--room-frames", type=int, default=10000)
    ap.add_argument("--room-objects", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--blocks", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=lambda t: [int(x) for x in t.split(",") if x.strip()],
                    default=[0, 1, 2, 3, 4], help="Demo rooms ('' for none).")
    ap.add_argument("--live", action="store_true", help="fr2_desk as a robot runs it (part 4)")
    ap.add_argument("--room-background", action="store_true",
                    help="part 3 with the optimisations in the background: add_frame's own time")
    ap.add_argument("--room-rate", type=float, default=0.0,
                    help="part 3's frames added at this rate (Hz; 0: as fast as add_frame returns)")
    ap.add_argument("--freeze-gc", action="store_true",
                    help="gc.freeze() before each replay (the room's, and --live's once the recording is read), as "
                         "docs/online.md recommends")
    ap.add_argument("--live-modes", type=lambda t: [x for x in t.split(",") if x], default=["background"],
                    help="background and/or inline")
    ap.add_argument("--live-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--live-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.live_child:
        live_child(args.live_child, args.live_out, args.freeze_gc)
        return 0
    from spdslam.solver import clear_caches

    out = {}

    def done(name, figures):
        """Keep a part's figures (written at once), then drop the compiled programs: one
        process holding every part's executables reaches the kernel's map limit (seen as
        "LLVM ERROR: Unable to allocate section memory")."""
        out[name] = figures
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
        clear_caches()

    if not args.skip_fr2:
        if FR2.is_dir():
            done("fr2_desk", fr2(args))
        else:
            print(f"fr2_desk: {FR2} not found, skipped")
    if args.live:
        if FR2.is_dir():
            done("fr2_desk_live", live(args))
        else:
            print(f"fr2_desk: {FR2} not found, --live skipped")
    if args.seeds:
        done("demo_rooms", demo_rooms(args))
    if not args.skip_room:
        done("room", room(args))
    if args.out:
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
