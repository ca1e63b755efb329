"""The test suite's wall and CPU time on a fresh clone (numba's cache empty), with this
environment's packages (no new venv: ``make test`` on a fresh clone also builds one).

    .venv/bin/python -m benchmarks.suite [pytest arguments]    # default: -n auto --dist loadgroup

The clone is of the committed HEAD (uncommitted changes are not in it) into a temporary
directory, removed afterwards. The CPU time is the clone's pytest and everything it waited
for (workers, notebook kernels, browsers, the wheel's environment); on a machine other
processes load, the wall time depends on them: the load average before and after is shown.
``make bench`` runs it once (``bench_suite``): one run takes the suite's time (minutes), so
it is one run, not a median; the machine's speed before and after (:func:`probe`) says how
far it compares with another run, and the core-seconds the cores sat idle and the host took
from them meanwhile (:func:`cpu_times`) say where a long wall time went that the CPU time
does not explain.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time

from .fresh import REPO
from .fresh import clone as fresh_clone
from .fresh import env as fresh_env

TARGET_S = 300.0


def probe() -> float:
    """CPU seconds of a fixed pure-Python loop (the least of three): the machine's speed at
    the time. On a shared virtual machine it varied from 0.51 to 0.9 s within minutes, and a
    suite's CPU time with it; a suite's figures are comparable only at a like probe."""
    def once():
        c0, s = time.process_time(), 0
        for i in range(10_000_000):
            s += i * i % 7
        return time.process_time() - c0
    return min(once() for _ in range(3))


def cpu_times() -> dict:
    """The machine's CPU seconds by kind since boot, all cores (``/proc/stat``; {} where
    there is none): ``steal`` is the time a virtual machine's cores were ready to run but
    the host ran something else -- a suite's wall time lengthened by the host's other
    guests, which its CPU time does not show."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return {}
    tick = os.sysconf("SC_CLK_TCK")
    names = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")
    return {n: int(v) / tick for n, v in zip(names, fields[1:])}


def run(argv: list[str]) -> dict:
    """One run of the suite on a fresh clone; its figures (also in results/suite.json)."""
    args = argv or ["-n", "auto", "--dist", "loadgroup"]
    with tempfile.TemporaryDirectory(prefix="leglib-suite-") as tmp:
        clone, head = fresh_clone(tmp)
        env = fresh_env(clone)   # its own (empty) numba cache beside its sources: the suite compiles first
        probe0 = probe()
        load0 = os.getloadavg()
        times0 = cpu_times()
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args], cwd=clone,
                              env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        load1 = os.getloadavg()
        times1 = cpu_times()
        probe1 = probe()
    cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
    spent = {k: times1[k] - times0[k] for k in times0 if k in times1}
    summary = (proc.stdout.strip().splitlines() or [""])[-1]
    result = {"commit": head, "args": args, "wall_s": wall, "cpu_s": cpu, "returncode": proc.returncode,
              "summary": summary, "load_before": load0, "load_after": load1, "probe_before_s": probe0, "probe_after_s": probe1,
              "machine_cpu_s": spent,
              "target_s": TARGET_S}
    ok = "ok  " if proc.returncode == 0 and wall <= TARGET_S else "MISS"
    print(f"[{ok}] suite on a fresh clone of {head}: {wall:.0f} s wall, {cpu:.0f} s CPU "
          f"(target {TARGET_S:.0f} s); load average {load0[0]:.1f} before, {load1[0]:.1f} after; machine probe "
          f"{probe0:.2f} s before, {probe1:.2f} s after (probe(): smaller is faster); "
          f"cores idle {spent.get('idle', float('nan')):.0f} s, stolen by the host "
          f"{spent.get('steal', float('nan')):.0f} s (core-seconds); {summary}")
    out = REPO / "benchmarks" / "results"
    out.mkdir(exist_ok=True)
    (out / "suite.json").write_text(json.dumps(result, indent=2))
    if proc.returncode:
        print(proc.stdout[-3000:], file=sys.stderr)
    return result


def main(argv: list[str]) -> int:
    return 0 if run(argv)["returncode"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
