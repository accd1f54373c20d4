"""Every method on every part of the real recordings: does one object ever fail a run?

    python3 benchmarks/every_method.py [--fr2 ../shared/data/tum_fr2_desk]
        [--fr3 ../shared/data/tum_fr3_cabinet] [--methods quadric-slam,multi-spd]
        [--parts whole,half1,half2,third1,third2,third3,cabinet]

For each part (fr2_desk whole, each half and each third of its frames; fr3_cabinet) and each
method of ``mapping.METHODS``, the run that ``spdslam run`` makes (``experiments.map_sequence``,
then ``experiments.write_run`` into a temporary folder). Prints one row per run: whether it
ended (``ok``) or raised (the exception, as the CLI would report it), the objects mapped and
not mapped (the reasons, counted by their first words), and the ATE of the input and of the
optimised trajectory (mm). A failure confined to one object must show as a row of its own
under ``failed``, never as an error of the run.
"""

from __future__ import annotations

import argparse
import collections
import re
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from spdslam.experiments import map_sequence, write_run
from spdslam.io import read_sequence
from spdslam.mapping import METHODS, RunSettings

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("whole", "half1", "half2", "third1", "third2", "third3", "cabinet")


def part_of(name: str, fr2, fr3):
    """The sequence of a part's name."""
    if name == "cabinet":
        return fr3
    n = len(fr2)
    if name == "whole":
        return fr2
    k, i = (2, int(name[-1]) - 1) if name.startswith("half") else (3, int(name[-1]) - 1)
    return fr2.subset(np.arange(i * n // k, (i + 1) * n // k))


def reasons(failed: dict) -> str:
    """The failures counted by their first words."""
    c = collections.Counter(re.split(r"[\d(:]", why)[0].strip() for why in failed.values())
    return "; ".join(f"{n}× {w}" for w, n in c.most_common())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fr2", default=str(ROOT / "../shared/data/tum_fr2_desk"))
    ap.add_argument("--fr3", default=str(ROOT / "../shared/data/tum_fr3_cabinet"))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--parts", default=",".join(PARTS))
    a = ap.parse_args()
    fr2, fr3 = read_sequence(a.fr2), read_sequence(a.fr3)
    print("| part | method | run | objects | not mapped | reasons | ATE input / optimised (mm) | s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
    for part in a.parts.split(","):
        seq = part_of(part, fr2, fr3)
        for method in a.methods.split(","):
            t = time.perf_counter()
            try:
                result, _ = map_sequence(seq, RunSettings.of(method))
                with tempfile.TemporaryDirectory() as out:
                    metrics = write_run(Path(out) / "run", seq, result, overlay=False)
            except Exception as e:  # noqa: BLE001 - the row says what ended the run
                dt = time.perf_counter() - t
                where = traceback.extract_tb(e.__traceback__)[-1]
                print(f"| {part} | {method} | **error** {type(e).__name__}: {e} "
                      f"({Path(where.filename).name}:{where.lineno}) | | | | | {dt:.1f} |", flush=True)
                continue
            dt = time.perf_counter() - t
            ate = metrics.get("ate", {})
            ate_s = (f"{1e3 * ate['input']['rmse']:.2f} / {1e3 * ate['optimized']['rmse']:.2f}"
                     if "input" in ate else "-")
            print(f"| {part} | {method} | ok | {len(result.objects)} | {len(result.failed)} | "
                  f"{reasons(result.failed)} | {ate_s} | {dt:.1f} |", flush=True)


if __name__ == "__main__":
    main()
