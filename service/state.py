"""Snapshots of the estimator's tracks on disk, so a restarted daemon goes on where it was.

A snapshot is one file, ``{state_dir}/estimator.state``: a small JSON header line (format
version, catalog fingerprint, stamp, object count) then the pickled
:meth:`~estimator.tracker.MultiViewEstimator.export_state`. It is written to a temporary file in
the same folder, flushed to disk and renamed over the old one, so a crash at any moment leaves
either the old snapshot or the new one, never half of one.

At start the snapshot is restored only if its catalog fingerprint matches the catalog being
served (tracks of other parts would be meaningless); otherwise it is set aside, not deleted.
Pickle executes code from the file it reads: the state folder must be writable by the daemon's
user only (docs/security.md); it is created with mode 0700.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from posefuse.estimator.core.errors import PosefuseError
from posefuse.estimator.tracker.snapshot import legacy_class

FORMAT = "posefuse-state/1"
FILENAME = "estimator.state"


class StateError(PosefuseError):
    """A snapshot that cannot be restored: which file, and why."""

    def __init__(self, path: Path, reason: str):
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


@dataclass(frozen=True)
class SnapshotInfo:
    path: Path
    objects: int
    last_stamp_ns: int | None
    bytes: int


def catalog_fingerprint(catalog) -> str:
    """sha256 over what makes a class: id, name, mesh (vertices, faces) and symmetries."""
    h = hashlib.sha256()
    for obj_id in sorted(catalog):
        m = catalog[obj_id]
        h.update(f"{obj_id}:{m.name}:{m.diameter:.9g}".encode())
        h.update(np.ascontiguousarray(m.mesh.vertices, np.float64).tobytes())
        h.update(np.ascontiguousarray(m.mesh.faces, np.int64).tobytes())
        h.update(np.ascontiguousarray(m.symmetries_discrete, np.float64).round(9).tobytes())
        h.update(repr(m.symmetries_continuous).encode())
    return h.hexdigest()


class _StateUnpickler(pickle.Unpickler):
    """Reads snapshots of this version and of the one before, whose classes lived in the
    estimator's older modules (:func:`estimator.tracker.snapshot.legacy_class`)."""

    def find_class(self, module: str, name: str):
        try:
            return super().find_class(module, name)
        except (AttributeError, ModuleNotFoundError):
            found = legacy_class(module, name)
            if found is None:
                raise
            return found


class StateStore:
    """Writes and reads the snapshot of one state folder for one catalog."""

    def __init__(self, state_dir: str | Path, fingerprint: str):
        self.dir = Path(state_dir)
        self.fingerprint = fingerprint
        self.path = self.dir / FILENAME

    def save(self, state: dict) -> SnapshotInfo:
        """Write the snapshot atomically (temporary file, fsync, rename)."""
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        body = pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)
        header = {
            "format": FORMAT,
            "catalog": self.fingerprint,
            "objects": len(state.get("tracks", {})),
            "last_stamp_ns": state.get("last_stamp_ns"),
        }
        tmp = self.path.with_name(f".{FILENAME}.{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            f.write(json.dumps(header).encode() + b"\n")
            f.write(body)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)
        try:  # the rename itself is durable once the folder is synced
            fd = os.open(self.dir, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError:
            pass
        return SnapshotInfo(self.path, header["objects"], header["last_stamp_ns"], len(body))

    def load(self) -> dict | None:
        """The saved state, or None when there is none. StateError when the file is not a
        snapshot or belongs to another catalog (the file is renamed ``*.rejected``)."""
        if not self.path.is_file():
            return None
        with open(self.path, "rb") as f:
            first = f.readline(4096)
            try:
                header = json.loads(first)
            except ValueError:
                header = None
            if not isinstance(header, dict) or header.get("format") != FORMAT:
                self._set_aside()
                raise StateError(self.path, f"not a {FORMAT} snapshot; set aside")
            if header.get("catalog") != self.fingerprint:
                self._set_aside()
                raise StateError(
                    self.path, "saved for another catalog (fingerprint differs); set aside"
                )
            try:
                return _StateUnpickler(f).load()
            except Exception as exc:
                self._set_aside()
                raise StateError(
                    self.path, f"unreadable ({type(exc).__name__}); set aside"
                ) from None

    def _set_aside(self) -> None:
        try:
            os.replace(self.path, self.path.with_suffix(".rejected"))
        except OSError:
            pass
