"""Why the results database could not be used. Both leave every run folder as it is: what was not recorded
is recorded later from the folders (``cell history --sync``; ``--rebuild`` for a damaged SQLite file)."""

from __future__ import annotations

from cell.errors import CellError


class ResultsError(CellError):
    """The results database cannot be used now; the message says which database and what to do."""


class ResultsUnavailable(ResultsError):
    """The database cannot be reached or written (server down, network lost, file or folder unwritable)."""


class ResultsDamaged(ResultsError):
    """The SQLite file is not a database or is corrupt: ``cell history --rebuild`` rebuilds it."""
