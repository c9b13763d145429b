"""Peak memory of one piece of work, measured from outside: torch's CPU allocations are invisible to tracemalloc,
and in a long-lived process freed memory is reused, so the work runs in a fresh interpreter whose resident set
is sampled every 0.5 ms by a thread."""
from __future__ import annotations

import subprocess
import sys

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
    """Resident-set growth (MiB) while the statement ``run`` executes, after ``setup`` (code that imports,
    warms up kernels and builds inputs, so none of that is counted) in a fresh Python process."""
    code = "import os, threading, time\nimport pidg\n" + setup + _PROBE.format(run=run)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise RuntimeError(f"memory probe failed:\n{result.stderr[-2000:]}")
    return float(result.stdout.strip().splitlines()[-1])
