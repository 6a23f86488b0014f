"""One exception root for the whole product; every leaf also inherits the matching builtin.

Messages say where, what, expected vs got (with units) and a hint.
"""
from __future__ import annotations


class CornermapError(Exception):
    """Root of every error cornermap raises on purpose."""

    exit_code = 1


class ConfigError(CornermapError, ValueError):
    """A workflow, catalog, drive file or params file is invalid. Lists every problem at once."""

    def __init__(self, where: str, problems: list[str]):
        self.where = where
        self.problems = list(problems)
        n = len(self.problems)
        body = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"{n} problem{'s' if n != 1 else ''} in {where}:\n{body}")

    def __reduce__(self):  # picklable across dask worker processes
        return (type(self), (self.where, self.problems))


class OptionError(ConfigError):
    """A command-line option's value is malformed or out of range: the command line itself is wrong. Exit 2, as
    click's and argparse's usage errors (``where`` names the option)."""

    exit_code = 2


class UnknownNameError(CornermapError, KeyError):
    """A stage, dataset or key that does not exist."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0]) if self.args else ""


class SchemaMismatchError(CornermapError, ValueError):
    """A table does not match its dataset's Arrow schema; lists every bad column."""


class DatasetIOError(CornermapError, OSError):
    """A dataset or file could not be read or written."""


class ObjectStoreError(DatasetIOError):
    """The object store could not be reached or refused the request (endpoint down, credentials missing or
    refused, bucket absent); the message names the URI and the endpoint. Raised by every operation of
    ``pipeline.storage.Store`` on an object-store root in place of the client's own exception (botocore, aiohttp);
    ``uri`` is the location asked for and ``line`` the part of the message after it (the endpoint and the cause)."""

    uri: str | None = None
    line: str | None = None

    @classmethod
    def at(cls, uri: str, line: str) -> "ObjectStoreError":
        err = cls(f"{uri}: {line}")
        err.uri, err.line = uri, line
        return err


class FormatError(CornermapError, ValueError):
    """A raw file is malformed (truncated, header lies, garbage bytes, wrong columns)."""


class StageError(CornermapError, RuntimeError):
    """A stage's compute failed; wraps the cause with the stage and partition."""


class DataQualityError(CornermapError, ValueError):
    """The data ran but failed a quality gate. The CLI exits 3."""

    exit_code = 3


class ReferenceFrameError(CornermapError, ValueError):
    """A trajectory or dataset whose coordinate frame is not stated and cannot be inferred."""


class PublishConflictError(CornermapError, FileExistsError):
    """Another publisher won the race, or a published version would be overwritten."""


class MapFormatError(CornermapError, ValueError):
    """A published map whose format version or layout this code does not understand."""


class ChecksumError(CornermapError, ValueError):
    """A file's sha256 differs from the one its manifest records."""


class IntegrityError(ChecksumError):
    """A file read for use does not match the digest recorded for it (tampered or corrupted)."""


class PathEscapeError(CornermapError, ValueError):
    """A path derived from input (a name, a manifest entry) resolves outside the directory it must stay in."""


class LimitError(CornermapError, ValueError):
    """An input or option asks for more work or memory than the stated limit allows."""


class RunLockedError(CornermapError, BlockingIOError):
    """Another run holds a whole-run lock (e.g. a map rebuild); this one stopped without writing. Exit 75
    (EX_TEMPFAIL: try again later)."""

    exit_code = 75
