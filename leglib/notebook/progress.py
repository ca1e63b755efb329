"""Progress lines while notebooks run: which notebook started, which section (a markdown
heading) its run has reached, a heartbeat while one cell runs long (a first compile of the
twin's kernel, a sweep), and how long the notebook took.

A :class:`StageLog` is given to nbclient as its ``on_cell_start`` / ``on_cell_executed``
hooks (through papermill, :func:`leglib.notebook.run.execute`); its lines go to standard
error, one per event, so they read the same in a terminal, a log file and CI, and lines of
two notebooks running at once stay apart (each starts with the notebook's number).
"""

from __future__ import annotations

import sys
import threading
import time

# seconds between "still running" lines while one cell runs
HEARTBEAT_S = 20.0


def _heading(cell) -> str | None:
    """The first markdown heading of a cell, without its hashes (None when it has none)."""
    if cell.get("cell_type") != "markdown":
        return None
    for line in str(cell.get("source", "")).splitlines():
        if line.lstrip().startswith("#"):
            return line.lstrip().lstrip("#").strip() or None
    return None


def _first_line(cell, width: int = 60) -> str:
    for line in str(cell.get("source", "")).splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            return line if len(line) <= width else line[: width - 3] + "..."
    return ""


def clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds} s" if seconds < 60 else f"{seconds // 60} min {seconds % 60:02d} s"


class StageLog:
    """Progress lines of one notebook run.

    Parameters
    ----------
    name : the notebook's name (its number starts every line)
    cells : the number of cells, for "cell k/n"
    heartbeat : seconds between "still running" lines while one cell runs (default
        :data:`HEARTBEAT_S`)
    stream : where lines go (standard error by default)
    """

    def __init__(self, name: str, cells: int, heartbeat: float | None = None, stream=None):
        heartbeat = HEARTBEAT_S if heartbeat is None else heartbeat
        if not heartbeat > 0:
            raise ValueError(f"heartbeat must be > 0 s, got {heartbeat!r}")
        self.tag = name[:2] if name[:2].isdigit() else name
        self.name, self.cells, self.heartbeat = name, int(cells), float(heartbeat)
        self.stream = stream
        self.lines: list[str] = []
        self._t0 = self._cell_t0 = time.monotonic()
        self._cell = None  # (index, first line) of the code cell running now
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._beat = None

    def say(self, text: str) -> None:
        line = f"[{self.tag}] {text}"
        with self._lock:
            self.lines.append(line)
            print(line, file=self.stream or sys.stderr, flush=True)

    def start(self) -> StageLog:
        self._t0 = time.monotonic()
        self.say(f"{self.name}: started")
        self._beat = threading.Thread(target=self._beating, name=f"stagelog-{self.tag}", daemon=True)
        self._beat.start()
        return self

    def finish(self, ok: bool = True) -> None:
        self._stop.set()
        if self._beat is not None:
            self._beat.join()
        took = clock(time.monotonic() - self._t0)
        self.say(f"{self.name}: done in {took}" if ok else f"{self.name}: FAILED after {took}")

    # nbclient's hooks (keyword arguments, see nbclient.NotebookClient.on_cell_start)
    def on_cell_start(self, cell, cell_index: int, **_) -> None:
        heading = _heading(cell)
        if heading is not None:
            self.say(f"{heading} (cell {cell_index + 1}/{self.cells}, {clock(time.monotonic() - self._t0)})")
        elif cell.get("cell_type") == "code":
            with self._lock:
                self._cell = (cell_index, _first_line(cell))
                self._cell_t0 = time.monotonic()

    def on_cell_executed(self, cell, cell_index: int, **_) -> None:
        with self._lock:
            self._cell = None

    def _beating(self) -> None:
        while not self._stop.wait(self.heartbeat):
            with self._lock:
                cell, since = self._cell, self._cell_t0
            if cell is not None and time.monotonic() - since >= self.heartbeat:
                index, text = cell
                self.say(f"  cell {index + 1}/{self.cells} running for {clock(time.monotonic() - since)}: {text}")
