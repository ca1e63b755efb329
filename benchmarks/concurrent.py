"""Two notebook-04 runs at once, repeated, under two CPU hogs: the lost wake-up that hung
them (leglib/notebook/wakeup.py) must not come back.

    .venv/bin/python -m benchmarks.concurrent [trials]     # default 20, about 15 minutes

A trial counts only if both runs end without a cell timeout: execute's retry after a
timeout (its RuntimeWarning) is made an error, so a hang cannot hide behind it.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RUN = ("import warnings; warnings.simplefilter('error', RuntimeWarning)\n"
       "from leglib.notebook.run import execute\n"
       "execute('notebooks/04_pid_sweeps.ipynb', {d!r}, dict(smoke=True, sweep_dir={d!r} + '/sweep', "
       "processed_dir={d!r} + '/processed'), html=False, timeout=240)")


def trial(root: Path) -> list:
    """Both runs at once; (return code or "hung", last error line) of each."""
    procs = [subprocess.Popen([sys.executable, "-c", RUN.format(d=str(root / str(k)))], cwd=REPO,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) for k in (0, 1)]
    out = []
    for p in procs:
        try:
            _, err = p.communicate(timeout=900)
            out.append((p.returncode, err.strip().splitlines()[-1][:160] if p.returncode and err.strip() else ""))
        except subprocess.TimeoutExpired:
            p.kill()
            out.append(("hung", ""))
    return out


def main(argv: list[str]) -> int:
    n = int(argv[0]) if argv else 20
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    ok = 0
    try:
        for k in range(n):
            t0 = time.monotonic()
            with tempfile.TemporaryDirectory(prefix="nb04pair_") as tmp:
                res = trial(Path(tmp))
            good = all(code == 0 for code, _ in res)
            ok += good
            print(f"trial {k + 1}/{n}: {'ok' if good else 'FAILED ' + str(res)} ({time.monotonic() - t0:.0f} s)",
                  flush=True)
    finally:
        for h in hogs:
            h.kill()
    print(f"{ok}/{n} trials: both runs completed")
    return 0 if ok == n else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
