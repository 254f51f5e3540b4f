"""One root error class for everything a user can get wrong, with subclasses that carry context.

The command line and the service map these to one clear message and a non-zero exit (or an
HTTP code) at the edge; inside the estimator they are raised at the boundary where input is
validated, before any state is touched.
"""

from __future__ import annotations

from pathlib import Path


class PosefuseError(Exception):
    """Root of all posefuse errors that describe bad input rather than a bug."""


class MeshError(PosefuseError):
    """A mesh file that is missing, unreadable or degenerate."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class CatalogError(PosefuseError):
    """A BOP object catalog (``models/`` + ``models_info.json``) that is missing or malformed."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class DatasetError(PosefuseError):
    """A folder that is not a readable BOP dataset, or a malformed file inside it."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class DatasetWarning(UserWarning):
    """A BOP file read with a repair the user should know of (for example rotations stored
    orthonormal only to 1e-2, as BOP's real datasets have them, projected to the nearest
    rotation). ``path`` names the file, ``count`` the entries repaired."""

    def __init__(self, path: str | Path, count: int, reason: str):
        self.path = str(path)
        self.count = count
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class ResultsError(PosefuseError):
    """A BOP results CSV with a malformed row. ``row`` is 1-based and counts the header."""

    def __init__(self, path: str | Path, row: int | None, reason: str):
        self.path = str(path)
        self.row = row
        self.reason = reason
        where = f"{self.path}, row {row}" if row is not None else self.path
        super().__init__(f"{where}: {reason}")
