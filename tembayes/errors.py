"""Exceptions that carry what a user needs to fix the problem."""

from __future__ import annotations

from pathlib import Path


class TembayesError(Exception):
    """Base class of every error tembayes raises on purpose.

    The CLI prints ``str(error)`` as its one-line reason and exits non-zero.
    """


class DataError(TembayesError, ValueError):
    """An input file or folder breaks the data contract (``docs/data-format.md``).

    Parameters
    ----------
    path : str or Path
        The offending file or folder.
    problem : str
        What is wrong, in plain words.
    hint : str
        What the user should do about it.
    line : int, optional
        1-based line number in the file (the header is line 1).
    column : str, optional
        Name of the offending column or key.
    """

    def __init__(self, path, problem, hint, *, line=None, column=None):
        self.path = Path(path)
        self.problem = problem
        self.hint = hint
        self.line = None if line is None else int(line)
        self.column = column
        where = str(self.path)
        if line is not None:
            where += f", line {line}"
        if column is not None:
            where += f", column '{column}'"
        super().__init__(f"{where}: {problem}. {hint}")


class ModelError(TembayesError, ValueError):
    """A model, rig description or parameter set is inconsistent."""
