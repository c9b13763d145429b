"""How the benchmarks measure: interleaved medians (for ratios on a noisy shared machine) and peak memory of one
piece of work in a fresh process."""
from __future__ import annotations

import statistics
import subprocess
import sys
import time
from collections.abc import Callable


def interleaved_medians(fns: dict[str, Callable[[], None]], repeats: dict[str, int]) -> dict[str, float]:
    """Median wall time (s) of each function, measured round-robin after one warm-up call each.

    The machine's capacity changes from minute to minute; interleaving makes every function see the same mix,
    so the ratios between them are meaningful even when the absolute times drift.
    """
    for fn in fns.values():
        fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    rounds = max(repeats.values())
    for r in range(rounds):
        for name, fn in fns.items():
            if r < repeats[name]:
                t0 = time.perf_counter()
                fn()
                times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(ts) for name, ts in times.items()}


_PROBE = """
rss = lambda: int(open('/proc/self/statm').read().split()[1]) * os.sysconf('SC_PAGE_SIZE')
base, peak, done = rss(), [0], threading.Event()
def sample():
    while not done.is_set():
        peak[0] = max(peak[0], rss()); time.sleep(0.0005)
th = threading.Thread(target=sample); th.start()
try:
    {run}
finally:
    done.set(); th.join()
print((max(peak[0], rss()) - base) / 2**20)
"""


def peak_rss_growth_mib(setup: str, run: str) -> float:
    """Peak memory measured from outside: torch's CPU allocations are invisible to tracemalloc, and in a long-lived
    process freed memory is reused, so the work runs in a fresh interpreter whose resident set is sampled every
    0.5 ms by a thread. Resident-set growth (MiB) while the statement ``run`` executes, after ``setup`` (code that imports,
    warms up kernels and builds inputs, so none of that is counted) in a fresh Python process."""
    code = "import os, threading, time\nimport pidg\n" + setup + _PROBE.format(run=run)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise RuntimeError(f"memory probe failed:\n{result.stderr[-2000:]}")
    return float(result.stdout.strip().splitlines()[-1])
