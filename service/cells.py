"""One process, several cells: a :class:`~service.daemon.Daemon` per cell on one Zenoh session.

The cells share the process's front end (one ONNX session; onnxruntime runs are thread-safe)
and the template banks; each has its own estimator, synchroniser, threads, snapshot
(``state_dir/{cell}`` when cells are listed) and election (:mod:`service.election`). The
HTTP API of the first cell is at ``/``, every cell's at ``/cells/{cell}/``.
"""

from __future__ import annotations

import logging
import threading

from posefuse.service.daemon import Daemon
from posefuse.service.settings import Settings, zenoh_config

log = logging.getLogger("posefuse.cells")


def cell_settings(settings: Settings, cell: str) -> Settings:
    """The settings of one cell: its key prefix and, when cells are listed, its own state
    folder ``state_dir/{cell}`` (shared with the daemons that back it up)."""
    update: dict = {"cell": cell}
    if (settings.cells or settings.standby_cells) and settings.state_dir is not None:
        update["state_dir"] = settings.state_dir / cell
    return settings.model_copy(update=update)


class CellSet:
    """The cells of one process. ``make_daemon(cell_settings) -> Daemon``."""

    def __init__(self, settings: Settings, make_daemon):
        self.settings = settings
        self.cells = settings.served_cells()
        self.daemons: dict[str, Daemon] = {
            cell: make_daemon(cell_settings(settings, cell)) for cell, _ in self.cells
        }
        self.ready = threading.Event()
        self._stop = threading.Event()

    def run(self) -> None:
        """Open the session and serve every cell until :meth:`stop`."""
        import zenoh

        with zenoh.open(zenoh_config(self.settings)) as session:
            threads = [
                threading.Thread(
                    target=self.daemons[cell].serve,
                    args=(session, primary),
                    daemon=True,
                    name=f"cell-{cell}",
                )
                for cell, primary in self.cells
            ]
            for t in threads:
                t.start()
            for d in self.daemons.values():
                d.ready.wait(30)
            self.ready.set()
            self._stop.wait()
            self.ready.clear()
            for d in self.daemons.values():
                d.stop()
            for t in threads:
                t.join(timeout=45)  # a daemon fuses its frame in flight, then saves

    def stop(self) -> None:
        self._stop.set()
