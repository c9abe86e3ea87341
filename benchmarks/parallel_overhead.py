"""Scheduling overhead of the executor seam (splatsearch.parallel) with no-op jobs, both backends.

    python benchmarks/parallel_overhead.py [--jobs 500] [--workers 2] [--backends local,ray]

For each backend: the workers are started and warmed with one round of jobs first (not timed);
then ``--jobs`` no-op jobs run through ``--workers`` workers (wall time / jobs: the per-job
cost a long run pays), and 50 single-job runs one after the other (the round trip of one job). A local Ray is started with the machine's CPUs. Note the load
(``uptime``) next to the numbers: other programs on the machine slow both.
"""

from __future__ import annotations

import argparse
import os
import time

from splatsearch.parallel import Job, make_executor, noop


def per_job_ms(ex, n: int) -> float:
    t0 = time.perf_counter()
    outs = list(ex.run([Job(str(i), noop, (i,)) for i in range(n)]))
    dt = time.perf_counter() - t0
    assert len(outs) == n and all(o.ok for o in outs)
    return 1e3 * dt / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--jobs", type=int, default=500)
    ap.add_argument("--workers", type=int, default=2, help="workers (>= 2: 1 runs the local backend in-process)")
    ap.add_argument("--backends", default="local,ray")
    a = ap.parse_args()
    print(f"load average: {os.getloadavg()}")
    for backend in a.backends.split(","):
        with make_executor(backend, a.workers) as ex:
            per_job_ms(ex, 2 * a.workers)  # start and warm the workers
            throughput = per_job_ms(ex, a.jobs)
            t0 = time.perf_counter()
            for i in range(50):  # one job at a time: the round trip of a single job
                list(ex.run([Job("x", noop, (i,))]))
            latency = 1e3 * (time.perf_counter() - t0) / 50
        print(f"{backend:5s} workers={a.workers}: {throughput:.2f} ms per job over {a.jobs} no-op jobs, "
              f"{latency:.2f} ms round trip of one job")
    print(f"load average: {os.getloadavg()}")


if __name__ == "__main__":
    main()
