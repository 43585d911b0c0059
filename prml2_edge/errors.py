"""The project's exception tree.

Setup and boundary problems raise a subclass of :class:`Prml2Error`; the CLI turns it
into one line and a non-zero exit (``--debug`` shows the traceback). On the hot path
stages return a status instead of raising (see the runtime).
"""


class Prml2Error(Exception):
    """Base of every error the project raises on purpose. The message is one line for the user."""


class ConfigError(Prml2Error):
    """A configuration, signal map or command-line value is wrong."""


class DataError(Prml2Error):
    """An input data file (CSV, CAN log) is missing, malformed or inconsistent."""


class DbcError(Prml2Error):
    """A DBC file does not parse or lacks what a signal map needs."""


class ModelError(Prml2Error):
    """A model or checkpoint is missing, corrupt or does not match the signal map."""


def install_hint(extra: str) -> str:
    """How to install the optional extra ``extra``, for one-line messages."""
    return f"pip install -c constraints.txt '.[{extra}]' (from the repository root)"


class MissingExtraError(Prml2Error):
    """An optional dependency (an extra) is not installed."""

    def __init__(self, module: str, extra: str, command: str | None = None, what: str | None = None) -> None:
        what = what or (f"'prml2 {command}'" if command else "this feature")
        super().__init__(f"{what} needs {module}, which is not installed: {install_hint(extra)}")
        self.module = module
        self.extra = extra


def require_extra(module: str, extra: str, what: str) -> None:
    """Import ``module`` or raise the one-line :class:`MissingExtraError` saying that ``what`` needs ``extra``."""
    import importlib

    try:
        importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(module, extra, what=what) from exc


def reject_unknown_keys(data, known, message: str, error: type[Exception] = ConfigError, **fields) -> None:
    """Raise ``error`` for the first key of ``data`` (sorted) that is not in ``known``; else return.

    ``message`` is a :meth:`str.format` template: ``{key}`` is the key's ``repr``, ``{known}``
    the known keys sorted and joined with ``", "``, any other field comes from ``fields``
    (substituted values are not parsed again, so a path with braces is safe).
    """
    known = set(known)
    unknown = sorted(set(data) - known)
    if unknown:
        raise error(message.format(key=repr(unknown[0]), known=", ".join(sorted(known)), **fields))


def first_line(exc: BaseException, limit: int | None = None) -> str:
    """The first line of ``str(exc)`` (stripped; the exception's type name when it has no text).

    ``limit`` cuts the line to that many characters (a backend's message can be a page long).
    """
    text = str(exc).strip()
    if not text:
        return type(exc).__name__
    line = text.splitlines()[0]
    return line if limit is None else line[:limit]
