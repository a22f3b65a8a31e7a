"""The exceptions promptdt raises: every one is a ``promptdt.Error``.

Each class is also the built-in exception that the same failure raised before this hierarchy
existed (``ValueError``, ``TypeError``, ``FileNotFoundError``, ``OSError``, ``RuntimeError``), so
``except ValueError`` keeps working, while ``except promptdt.Error`` catches everything promptdt
refuses and nothing else. The messages name the file, field, argument or shape at fault.

The native module raises these classes too (``crates/python/src/errors.rs`` imports them by name):
an error of the library crates is sorted by what caused it, an I/O error anywhere in its chain of
causes making it a ``FileError`` (or ``NotFoundError`` for a missing file) with the ``errno`` of
the system call.
"""
from __future__ import annotations

__all__ = [
    "Error",
    "InvalidInputError",
    "ArgumentTypeError",
    "NotFoundError",
    "FileError",
    "StateError",
]


class Error(Exception):
    """Base of every exception promptdt raises."""


class InvalidInputError(Error, ValueError):
    """A value that promptdt refuses: an argument out of range, a file's field or an array's
    shape that does not fit, an unknown family, method or task, a configuration that does not
    validate. Also a ``ValueError``."""


class ArgumentTypeError(Error, TypeError):
    """An argument of the wrong type (a float where a task index is expected, a string where a
    list is). Also a ``TypeError``."""


class FileError(Error, OSError):
    """Reading or writing a file or directory failed in the operating system (permissions, disk
    full, a directory where a file is expected, ...). Also an ``OSError``; ``errno`` is set when
    the system call gave one."""


class NotFoundError(FileError, FileNotFoundError):
    """A file or directory that is not there: a run directory, a dataset, a checkpoint. Also a
    ``FileNotFoundError`` (and so an ``OSError``)."""


class StateError(Error, RuntimeError):
    """A call out of order (``step`` before ``reset``), a command that failed as a whole, or an
    internal state promptdt cannot go on from. Also a ``RuntimeError``."""
