"""The imports a mapping command pays before its first step (docs/performance.md, "Importing
JAX"): ``python -X importtime`` of ``spdslam.mapping`` in fresh processes, the median of each
of ``--repeats`` runs for the modules that dominate (ml_dtypes' extension, JAX, jaxlie,
spdslam.mapping), with the environment's packages and, for each ``--path DIR``, with DIR
first on ``PYTHONPATH`` (e.g. another ml_dtypes unpacked there:
``pip download ml_dtypes==0.7.0 --no-deps -d W && python -m zipfile -e W/*.whl DIR``).

    python3 benchmarks/imports.py [--repeats 5] [--path DIR ...] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

MODULES = ("ml_dtypes._ml_dtypes_ext", "ml_dtypes", "jax", "jaxlie", "spdslam.mapping")


def one_run(path: str | None) -> dict:
    """Cumulative import time (s) of each of ``MODULES`` in one fresh process."""
    env = dict(os.environ)
    if path:
        env["PYTHONPATH"] = path + os.pathsep + env.get("PYTHONPATH", "")
    code = "import spdslam.mapping, ml_dtypes; print(ml_dtypes.__version__)"
    p = subprocess.run([sys.executable, "-X", "importtime", "-c", code], env=env, capture_output=True, text=True,
                       check=True)
    out = {"ml_dtypes_version": p.stdout.strip()}
    for line in p.stderr.splitlines():
        if not line.startswith("import time:"):
            continue
        _, cum_us, name = (x.strip() for x in line[len("import time:"):].split("|"))
        if name in MODULES:
            out[name] = int(cum_us) / 1e6
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--path", action="append", default=[], help="a folder put first on PYTHONPATH")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    rows = []
    for path in [None, *a.path]:
        runs = [one_run(path) for _ in range(a.repeats)]
        row = {"path": path or "(the environment's)", "ml_dtypes_version": runs[0]["ml_dtypes_version"],
               **{m: statistics.median(r.get(m, float("nan")) for r in runs) for m in MODULES}}
        rows.append(row)
        print(f"{row['path']} (ml_dtypes {row['ml_dtypes_version']}): " +
              ", ".join(f"{m} {row[m]:.3f} s" for m in MODULES))
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"repeats": a.repeats, "rows": rows}, indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
