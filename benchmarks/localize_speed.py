"""How long ``mapping.localize_objects`` takes on fr2_desk's halves, this checkout against an
older commit (docs/map-reuse.md).

fr2_desk's two halves are mapped once (this checkout); then each half's first 5, 8, 12 and all
objects are localised against the other half's map, under SE(3) and Sim(3), as a
``LocalizingMapper``'s tries are. Each checkout (the older one in a ``git worktree`` removed
afterwards) times every case in a process of its own, best of ``--repeats``, alternating
checkouts; the answers (transform to 1e-9, scale, matches, rival) must be equal.

    python3 benchmarks/localize_speed.py --against be0e3eb [--repeats 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FR2 = ROOT / "../shared/data/tum_fr2_desk"
SIZES = (5, 8, 12, None)

#: What each checkout runs: the cases from the pickled maps, each timed ``repeats`` times.
CHILD = r"""
import os, pickle, sys, time
import numpy as np
import spdslam
assert spdslam.__file__.startswith(os.getcwd()), (spdslam.__file__, os.getcwd())
from spdslam.mapping import LocalizationError, localize_objects
maps, sizes, repeats = pickle.load(open(sys.argv[1], "rb"))
rows = []
for sim3 in (False, True):
    for a, b in ((0, 1), (1, 0)):
        for m in sizes:
            objs = maps[a][:m]
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                try:
                    loc = localize_objects(objs, maps[b], sim3=sim3)
                    answer = (np.round(loc.T_map_sequence, 9).tolist(), round(loc.scale, 9),
                              [tuple(map(int, p)) for p in loc.matches], int(loc.runner_up))
                except LocalizationError as e:
                    answer = str(e)
                best = min(best, time.perf_counter() - t0)
            rows.append({"sim3": sim3, "recording": a + 1, "map": b + 1, "objects": len(objs),
                         "seconds": best, "answer": answer})
pickle.dump(rows, open(sys.argv[2], "wb"))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--against", required=True, help="the older commit")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    from spdslam.io import read_sequence
    from spdslam.mapping import RunSettings, run_sequence

    fr2 = read_sequence(FR2)
    n = len(fr2)
    settings = RunSettings.of("multi-spd")
    maps = [run_sequence(fr2.subset(np.arange(0, n // 2)), settings).objects,
            run_sequence(fr2.subset(np.arange(n // 2, n)), settings).objects]
    tmp = Path(tempfile.mkdtemp(prefix="spdslam_localize_"))
    wt = tmp / "against"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(wt), a.against],
                   check=True, capture_output=True)
    try:
        cases = tmp / "cases.pkl"
        pickle.dump((maps, SIZES, 1), open(cases, "wb"))
        results: dict = {}
        for _ in range(2):  # alternating, the better of two processes per checkout
            for name, path in (("this checkout", ROOT), (a.against, wt)):
                pickle.dump((maps, SIZES, a.repeats), open(cases, "wb"))
                env = {**os.environ, "PYTHONPATH": str(path)}
                out = tmp / "rows.pkl"
                subprocess.run([sys.executable, "-c", CHILD, str(cases), str(out)], env=env, check=True, cwd=path)
                rows = pickle.load(open(out, "rb"))
                if name in results:
                    for old, new in zip(results[name], rows):
                        old["seconds"] = min(old["seconds"], new["seconds"])
                else:
                    results[name] = rows
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(wt)], check=False)
    mine, theirs = results["this checkout"], results[a.against]
    print(f"| case | objects | this checkout (ms) | {a.against} (ms) | ratio | same answer |")
    print("| --- | --- | --- | --- | --- | --- |")
    table = []
    for x, y in zip(mine, theirs):
        case = f"{'Sim(3)' if x['sim3'] else 'SE(3)'}, half {x['recording']} → {x['map']}"
        same = x["answer"] == y["answer"]
        print(f"| {case} | {x['objects']} | {1e3 * x['seconds']:.1f} | {1e3 * y['seconds']:.1f} | "
              f"{y['seconds'] / x['seconds']:.2f}× | {'yes' if same else 'NO'} |")
        table.append({"case": case, "objects": x["objects"], "seconds": x["seconds"],
                      "seconds_against": y["seconds"], "same_answer": same})
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"against": a.against, "rows": table}, indent=1) + "\n")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
