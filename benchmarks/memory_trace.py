"""Run the pipeline's CLI in a subprocess and print every log line with the process's
resident memory (GB) when it appeared, then the peak (ru_maxrss of the child) against
the estimate of :mod:`pipeline._util.resources` for the mesh it made.

    python benchmarks/memory_trace.py configs/cantilever.yaml --set mesh.size=0.00211 \
        --set modes.count=20 --set modes.method=multigrid

The arguments after the config are passed to ``python -m pipeline -v run``. The
resident memory is sampled every 0.1 s beside the log, so each line also shows the
largest resident memory since the line before (the peak of the step it closes).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def rss_gb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e9
    except (OSError, ValueError, IndexError):
        return 0.0


def main() -> None:
    with tempfile.TemporaryDirectory() as work:
        cmd = [sys.executable, "-m", "pipeline", "-v", "run", sys.argv[1], "-o",
               str(Path(work) / "out.h5"), *sys.argv[2:]]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                text=True)
        window = [0.0]
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                window[0] = max(window[0], rss_gb(proc.pid))
                time.sleep(0.1)

        threading.Thread(target=sample, daemon=True).start()
        for line in proc.stderr:
            now = rss_gb(proc.pid)
            print(f"{time.perf_counter() - t0:7.1f} s {now:6.2f} GB (step max "
                  f"{max(window[0], now):6.2f}) | {line.rstrip()[:150]}", flush=True)
            window[0] = now
        proc.wait()
        done.set()
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6
        print(f"exit {proc.returncode}; wall {time.perf_counter() - t0:.1f} s; "
              f"peak (ru_maxrss) {peak:.2f} GB")


if __name__ == "__main__":
    main()
