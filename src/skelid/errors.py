"""One exception family for everything a user can fix.

Every error a person can act on derives from :class:`SkelidError`. Its message
is one line naming the file, marker or parameter, the problem, and the fix;
the command line prints exactly that line and exits with status 2. Any other
exception is a bug and keeps its traceback (exit status 1).

Warnings a user should see (poorly identified parameters, many dropped frames,
units guessed, residuals that look like soft-tissue artefact) are
:class:`SkelidWarning` and are also recorded in JSON results.
"""

from __future__ import annotations


class SkelidError(Exception):
    """Base class: a problem with the user's input that the user can fix.

    Parameters
    ----------
    problem : str
        What is wrong, naming the file, line, marker or parameter.
    fix : str, optional
        What the user can do about it.
    """

    def __init__(self, problem: str, fix: str | None = None):
        self.problem = " ".join(str(problem).split())
        self.fix = " ".join(fix.split()) if fix else None
        super().__init__(self.one_line())

    def one_line(self) -> str:
        """The single line the command line prints."""
        return f"{self.problem} (fix: {self.fix})" if self.fix else self.problem


class FormatError(SkelidError):
    """A file is malformed or not of the format its reader expects."""


class ModelError(SkelidError):
    """A model description is invalid (unknown joint type, dangling parent, ...)."""


class DataError(SkelidError):
    """The data cannot serve the model: a missing marker, NaN frames, wrong units."""


class IdentifiabilityError(SkelidError):
    """A parameter cannot be identified from the data (no information, no solution)."""


class SettingError(SkelidError, ValueError):
    """An estimator setting has a value it cannot use (names the setting)."""


class NotFittedError(SkelidError, AttributeError):
    """A fitted attribute or result was asked for before ``fit``."""


class ConvergenceError(SkelidError):
    """The fit did not converge, so no interval can be reported."""


class StreamError(SkelidError):
    """A live stream cannot be found, does not match what it must carry, or stopped sending."""


class SkelidWarning(UserWarning):
    """A problem the user should know about that does not stop the computation."""


def headline(message, width: int) -> str:
    """A message in one line of at most ``width`` characters: its text, or its head ending in ``...``.

    A longer text is cut at its last clause boundary (``; ``, ``: ``, `` (``, ``, ``) that keeps at
    least half the line, else at a word.
    """
    text = " ".join(str(message).split())
    if len(text) <= width:
        return text
    cut = text[:width - 3]
    for sep in ("; ", ": ", " (", ", "):
        k = cut.rfind(sep)
        if k >= width // 2:
            return cut[:k].rstrip(" ,;:") + "..."
    k = cut.rfind(" ")
    return (cut[:k] if k > 0 else cut).rstrip(" ,;:") + "..."
