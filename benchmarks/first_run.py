"""The first run against the later ones: fr2_desk (``../shared/data/tum_fr2_desk``) mapped by
``spdslam run`` and replayed through the online mapper, each in a fresh process, with the
compilation cache (``SPDSLAM_CACHE_DIR``) empty (*cold*), filled by an earlier process
(*warm*), and in the process that already ran it (*hot*).

1. ``spdslam run`` on fr2_desk: wall time of the command, cold then warm.
2. The online replay at the sequence's 31 Hz (``benchmarks/online.py``'s figures: median,
   99th percentile and maximum time per frame, the largest delay behind the camera):
   cold; warm; hot (a second replay in the warm process); warm with
   ``OnlineMapper.warmup`` before the first frame (a 300-frame synthetic room with 40
   objects, seen with fr2_desk's camera); and from an empty cache after
   ``spdslam warmup ../shared/data/tum_fr2_desk``, without and with the in-process warm-up.

    python3 benchmarks/first_run.py [--json FILE] [--skip-run] [--skip-online]

Each case runs in its own process with its own cache folder under a temporary directory.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout
sys.path.insert(0, str(HERE))

FR2 = HERE.parent / ".." / "shared" / "data" / "tum_fr2_desk"
WARMUP_ROOM = dict(seed=0, frames=300, objects=40)


def child(cache: str, warmup: bool, replays: int) -> None:
    """One process: the replays of fr2_desk (JSON on the last line of stdout)."""
    os.environ["SPDSLAM_CACHE_DIR"] = cache
    from online import stats

    from spdslam.io import read_sequence
    from spdslam.mapping import OnlineMapper
    from spdslam.synthetic import make_room_sequence

    seq = read_sequence(FR2)
    by_frame: dict = {}
    for d in seq.detections:
        by_frame.setdefault(d.frame, []).append(d)
    out = []
    for rep in range(replays):
        m = OnlineMapper(seq.camera, seq.priors, "multi-spd", associate="auto")
        w = None
        if warmup and rep == 0:
            room = make_room_sequence(WARMUP_ROOM["seed"], WARMUP_ROOM["frames"], WARMUP_ROOM["objects"],
                                      camera=seq.camera, truncation=True)
            w = m.warmup(room)
        for i in range(len(seq)):
            m.add_frame(seq.timestamps[i], seq.poses_tum[i], detections=by_frame.get(i, ()))
        r = stats(m.records, seq.timestamps)
        r["warmup_s"] = w
        out.append(r)
    print(json.dumps(out))


def _replay(cache: Path, warmup: bool = False, replays: int = 1) -> list:
    cmd = [sys.executable, __file__, "--child", str(cache), "--replays", str(replays)]
    if warmup:
        cmd.append("--warmup")
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _spdslam(args: list, cache: Path) -> float:
    env = {**os.environ, "SPDSLAM_CACHE_DIR": str(cache)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "from spdslam.cli import app; app(prog_name='spdslam')", *args],
                   env=env, check=True, capture_output=True, text=True)
    return time.perf_counter() - t0


def _line(name: str, r: dict) -> str:
    w = f", warm-up {r['warmup_s']:.1f} s" if r.get("warmup_s") else ""
    return (f"{name}: median {r['median_ms']:.3g} ms, p99 {r['p99_ms']:.3g} ms, max {r['max_ms']:.0f} ms "
            f"per frame; largest delay {r['max_delay_s']:.2f} s, last frame's {r['last_delay_s']:.2f} s{w}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--skip-run", action="store_true")
    ap.add_argument("--skip-online", action="store_true")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--warmup", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--replays", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.warmup, args.replays)
        return 0
    if not FR2.is_dir():
        print(f"skipped: {FR2} is absent")
        return 0
    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="spdslam-first-run-") as tmp:
        tmp = Path(tmp)
        if not args.skip_run:
            cache = tmp / "run-cache"
            for case in ("cold", "warm"):
                seconds = _spdslam(["run", str(FR2), "--out", str(tmp / f"run-{case}")], cache)
                out[f"run_{case}_s"] = seconds
                print(f"spdslam run fr2_desk, {case} cache: {seconds:.1f} s", flush=True)
        if not args.skip_online:
            cache = tmp / "online-cache"
            cases = [("cold", cache, False, 1), ("warm, then hot", cache, False, 2),
                     ("warm, OnlineMapper.warmup first", cache, True, 1)]
            for name, c, w, n in cases:
                rs = _replay(c, w, n)
                for k, r in enumerate(rs):
                    label = name.split(", ")[k] if n > 1 else name
                    out[f"online {label}"] = r
                    print(_line(f"online, {label}", r), flush=True)
            cache = tmp / "warmup-cache"
            seconds = _spdslam(["warmup", str(FR2)], cache)
            out["spdslam_warmup_s"] = seconds
            print(f"spdslam warmup (empty cache): {seconds:.1f} s", flush=True)
            for name, w in (("after spdslam warmup", False), ("after spdslam warmup, OnlineMapper.warmup first", True)):
                r = _replay(cache, w)[0]
                out[f"online {name}"] = r
                print(_line(f"online, {name}", r), flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
