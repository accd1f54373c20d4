"""A pytest plugin that logs the process's memory mappings and resident size every 25 tests
(docs/performance.md, "Long processes"):

    PYTHONPATH=benchmarks python3 -m pytest -q -p mapcount      # -> mapcount.log (MAPCOUNT_LOG)

Each line: ``<tests run> <node id> maps=<lines of /proc/self/maps> rss_kb=<VmRSS>``; the
largest ``maps`` is the figure to compare with ``vm.max_map_count``. Linux only.
"""

from __future__ import annotations

import os

_EVERY = 25
_count = [0]


def pytest_runtest_teardown(item):
    _count[0] += 1
    if _count[0] % _EVERY:
        return
    with open("/proc/self/maps", "rb") as f:
        maps = sum(1 for _ in f)
    with open("/proc/self/status") as f:
        rss = next(line for line in f if line.startswith("VmRSS")).split()[1]
    with open(os.environ.get("MAPCOUNT_LOG", "mapcount.log"), "a") as f:
        f.write(f"{_count[0]} {item.nodeid} maps={maps} rss_kb={rss}\n")
