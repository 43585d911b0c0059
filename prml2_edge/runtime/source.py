"""CAN sources: a live python-can bus, or a log file replayed through a python-can virtual bus.

:func:`open_bus` opens any python-can interface by name (``socketcan``, ``pcan``, ``kvaser``,
``vector``, ``virtual``, ...). :class:`LogReplay` plays a log (``.log``, ``.asc``, ``.blf``,
``.trc``, ``.csv``, ``.mf4`` with asammdf, ... whatever ``can.LogReader`` reads) into the *same* receive path the live
runtime uses: a feeder thread reads the file and sends every frame on a sender bus; the
pipeline receives them on a second bus on the same unique virtual channel, timestamps
preserved. ``max_in_flight`` bounds the frames between the two (backpressure, so a long log
never fills memory); the end of the log is detected by counting frames sent and received
once the feeder is done, so no frame is lost or left behind.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import sys
import threading
import time
import uuid
from pathlib import Path

import can

from prml2_edge.errors import ConfigError, DataError, first_line, require_extra

log = logging.getLogger(__name__)

LOG_SUFFIXES = (".asc", ".blf", ".csv", ".db", ".log", ".mf4", ".trc")


def open_bus(interface: str, channel: str, bitrate: int | None = None, fd: bool = False,
             **kwargs) -> can.BusABC:
    """Open a python-can bus; any failure becomes one :class:`ConfigError` line."""
    options = dict(kwargs)
    if bitrate is not None:
        options["bitrate"] = bitrate
    if fd:
        options["fd"] = True
    try:
        return can.Bus(interface=interface, channel=channel, receive_own_messages=False, **options)
    except Exception as exc:  # backends raise CanError, OSError, ImportError, ValueError, ...
        first = first_line(exc)
        hint = " (is the link up? see deploy/can-setup.sh)" if interface == "socketcan" else ""
        raise ConfigError(f"cannot open CAN interface {interface!r} channel {channel!r}: {first}{hint}") from exc


class BusSource:
    """Frames from a python-can bus; :meth:`step` returns one frame or None on timeout. Never raises."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.received = 0
        self.errors = 0
        self.last_error = ""

    def step(self, timeout_s: float = 0.1) -> can.Message | None:
        try:
            msg = self.bus.recv(timeout=timeout_s)
        except Exception as exc:  # a bus error must not end the loop: count it, back off briefly
            self.errors += 1
            self.last_error = first_line(exc)
            time.sleep(min(timeout_s, 0.05))
            return None
        if msg is not None:
            self.received += 1
        return msg

    def close(self) -> None:
        self.bus.shutdown()


@contextlib.contextmanager
def _quiet_mdf_teardown(path: Path):
    """asammdf's ``MDF4.__del__`` raises AttributeError on an object whose ``__init__`` failed (a cut-off or
    corrupt .mf4), which Python prints as a traceback after the one-line error; drop just that report."""
    if path.suffix.lower() != ".mf4":
        yield
        return
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        if not (isinstance(unraisable.exc_value, AttributeError) and type(unraisable.object).__name__ == "function"
                and "MDF4.__del__" in repr(unraisable.object)):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        gc.collect()
        sys.unraisablehook = previous


def check_log(path: str | Path) -> Path:
    """Refuse a missing file or a suffix python-can cannot read, in one line."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: CAN log not found")
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    if not suffixes or suffixes[-1] not in LOG_SUFFIXES:
        raise DataError(f"{path}: unknown CAN log format; python-can reads {', '.join(LOG_SUFFIXES)} (optionally .gz)")
    if suffixes[-1] == ".mf4":  # python-can's MF4 reader needs asammdf (the mf4 extra)
        require_extra("asammdf", "mf4", f"{path}: an ASAM MDF4 log")
    return path


def truncation_problem(path: str | Path) -> str | None:
    """Why the log looks cut off, or None: python-can silently stops at the end of a cut-off
    ``.asc``, ``.blf`` or ``.trc``, so look at the end of the file itself.

    Text formats (``.log``, ``.asc``, ``.trc``, ``.csv``) must end with a newline (``.asc``
    with ``End TriggerBlock``); a ``.blf`` must be as long as its header says. Compressed
    (``.gz``) logs are checked by gzip itself.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        size = path.stat().st_size
        if suffix == ".blf":
            from can.io.blf import BLFReader

            reader = BLFReader(str(path))
            try:
                want = int(reader.file_size)
            finally:
                reader.stop()
            return None if size >= want else f"file is {size} bytes, its header says {want}: truncated"
        if suffix in (".log", ".asc", ".trc", ".csv"):
            with open(path, "rb") as f:
                f.seek(max(size - 64, 0))
                tail = f.read()
            if size and not tail.endswith(b"\n"):
                return "the last line is incomplete: truncated"
            if suffix == ".asc" and b"End TriggerBlock" not in tail:
                return "no 'End TriggerBlock' at the end: truncated"
    except Exception as exc:  # the reader will report a header it cannot read
        return f"cannot check the end of the file ({first_line(exc, 200)})"
    return None


def scan_log(path: str | Path) -> tuple[int, float, float, str | None]:
    """Read a log once: ``(frames, first_timestamp_s, last_timestamp_s, problem)``.

    ``problem`` is None for a complete, readable log, else one line naming the file and what
    is wrong (the frames before the problem are counted). Never raises on a bad file.
    """
    path = check_log(path)
    n = 0
    first = last = 0.0
    problem = None
    with _quiet_mdf_teardown(path):
        try:
            with can.LogReader(str(path)) as reader:
                for msg in reader:
                    if n == 0:
                        first = msg.timestamp
                    last = msg.timestamp
                    n += 1
        except Exception as exc:
            problem = f"{path}: cannot read CAN log after {n} frames ({first_line(exc, 200)})"
    if problem is None:
        cut = truncation_problem(path)
        if cut is not None:
            problem = f"{path}: CAN log cut short after {n} frames ({cut})"
    if problem is None and n == 0:
        problem = f"{path}: CAN log holds no frames"
    return n, first, last, problem


def count_log_frames(path: str | Path) -> tuple[int, float, float]:
    """Read a log once: ``(frames, first_timestamp_s, last_timestamp_s)``; a malformed log is a :class:`DataError`."""
    n, first, last, problem = scan_log(path)
    if problem is not None:
        raise DataError(problem)
    return n, first, last


class LogReplay:
    """Play a CAN log through a python-can virtual bus pair; use as a context manager.

    Parameters
    ----------
    path:
        The log.
    realtime:
        Keep the log's timing (scaled by ``speed``); otherwise as fast as the pipeline takes it.
    speed:
        Playback speed factor with ``realtime`` (2.0 = twice as fast).
    max_in_flight:
        Frames sent but not yet received at most (backpressure).

    :meth:`step` returns the next frame (None on timeout); :attr:`finished` becomes True once
    the feeder has sent the whole log and every frame has been received. A log that breaks
    midway sets :attr:`error` (the frames before it are still delivered).
    """

    def __init__(self, path: str | Path, realtime: bool = False, speed: float = 1.0, max_in_flight: int = 4096,
                 channel: str | None = None) -> None:
        self.path = check_log(path)
        if not speed > 0:
            raise ConfigError(f"replay speed must be > 0, got {speed}")
        self.realtime = realtime
        self.speed = float(speed)
        self.channel = channel or f"prml2-replay-{uuid.uuid4().hex}"
        self.sent = 0
        self.received = 0
        self.error: str | None = None
        self._slots = threading.Semaphore(max_in_flight)
        self._stop = threading.Event()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._tx: can.BusABC | None = None
        self._rx: can.BusABC | None = None

    def start(self) -> LogReplay:
        # The receiver exists before the first frame is sent: nothing can be missed.
        self._rx = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=True)
        self._tx = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=True)
        self._thread = threading.Thread(target=self._feed, name="prml2-log-feeder", daemon=True)
        self._thread.start()
        return self

    def __enter__(self) -> LogReplay:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _feed(self) -> None:
        with _quiet_mdf_teardown(self.path):
            self._feed_log()

    def _feed_log(self) -> None:
        try:
            with can.LogReader(str(self.path)) as reader:
                t_log0 = t_wall0 = None
                for msg in reader:
                    if self.realtime:
                        if t_log0 is None:
                            t_log0, t_wall0 = msg.timestamp, time.monotonic()
                        delay = t_wall0 + (msg.timestamp - t_log0) / self.speed - time.monotonic()
                        if delay > 0 and self._stop.wait(delay):
                            return
                    while not self._slots.acquire(timeout=0.1):
                        if self._stop.is_set():
                            return
                    if self._stop.is_set():
                        return
                    self._tx.send(msg)  # type: ignore[union-attr]
                    self.sent += 1
        except Exception as exc:  # a malformed log: deliver what came before, report it at the end
            self.error = f"{self.path}: cannot read CAN log after {self.sent} frames ({first_line(exc, 200)})"
        finally:
            self._done.set()

    @property
    def finished(self) -> bool:
        """True once the feeder is done and every frame it sent has been received."""
        return self._done.is_set() and self.received >= self.sent

    def step(self, timeout_s: float = 0.1) -> can.Message | None:
        """Next frame in log order, or None when none arrived within ``timeout_s`` [s]."""
        if self.finished:
            return None
        msg = self._rx.recv(timeout=timeout_s)  # type: ignore[union-attr]
        if msg is not None:
            self.received += 1
            self._slots.release()
        return msg

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for bus in (self._tx, self._rx):
            if bus is not None:
                bus.shutdown()
        self._tx = self._rx = None
