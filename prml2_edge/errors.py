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


class MissingExtraError(Prml2Error):
    """An optional dependency (an extra) is not installed."""

    def __init__(self, module: str, extra: str, command: str | None = None) -> None:
        what = f"'prml2 {command}'" if command else "this feature"
        super().__init__(
            f"{what} needs {module}, which is not installed: "
            f"pip install -c constraints.txt 'prml2-edge[{extra}]' (from the repository root)"
        )
        self.module = module
        self.extra = extra
