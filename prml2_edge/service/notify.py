"""systemd ``sd_notify`` over the notify socket, with no extra dependency.

systemd passes ``NOTIFY_SOCKET`` (a filesystem path, or ``@name`` for the abstract
namespace) to a ``Type=notify`` service; the service sends datagrams such as
``READY=1``, ``STATUS=...``, ``WATCHDOG=1`` and ``STOPPING=1``. With ``WatchdogSec=``
set, systemd also passes ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``) and restarts the
service when no ``WATCHDOG=1`` arrives within that time; we ping at half the interval.

Outside systemd (no ``NOTIFY_SOCKET``) every call is a cheap no-op.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Mapping

log = logging.getLogger(__name__)


class SystemdNotifier:
    """Send sd_notify messages; never raises on the hot path (failures are counted)."""

    def __init__(self, environ: Mapping[str, str] | None = None, clock=time.monotonic) -> None:
        env = os.environ if environ is None else environ
        self._clock = clock
        self.address = self._parse_address(env.get("NOTIFY_SOCKET", ""))
        self.watchdog_interval_s = self._parse_watchdog(env)
        self.send_failures = 0
        self.sent = 0
        self._last_ping = -float("inf")
        self._sock: socket.socket | None = None
        if self.address is not None:
            try:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            except OSError as exc:  # pragma: no cover - AF_UNIX always exists on Linux
                log.warning("sd_notify disabled: %s", exc)
                self.address = None

    @staticmethod
    def _parse_address(value: str) -> str | None:
        if not value:
            return None
        if value.startswith("@"):
            return "\0" + value[1:]  # abstract namespace socket
        if value.startswith("/"):
            return value
        log.warning("ignoring NOTIFY_SOCKET=%r (neither a path nor @abstract)", value)
        return None

    @staticmethod
    def _parse_watchdog(env: Mapping[str, str]) -> float | None:
        usec = env.get("WATCHDOG_USEC")
        if not usec:
            return None
        pid = env.get("WATCHDOG_PID")
        if pid and pid.isdigit() and int(pid) != os.getpid():
            return None  # the watchdog is meant for another process
        try:
            value = int(usec)
        except ValueError:
            return None
        return value / 1e6 if value > 0 else None

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, *fields: str) -> bool:
        """Send ``KEY=value`` fields in one datagram; True when sent."""
        if self._sock is None or self.address is None:
            return False
        try:
            self._sock.sendto("\n".join(fields).encode(), self.address)
        except OSError:
            self.send_failures += 1
            return False
        self.sent += 1
        return True

    def ready(self, status: str = "") -> bool:
        fields = ["READY=1"] + ([f"STATUS={status}"] if status else [])
        return self.notify(*fields)

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def maybe_ping(self) -> bool:
        """Feed the watchdog when half its interval has passed since the last ping."""
        if self.watchdog_interval_s is None:
            return False
        now = self._clock()
        if now - self._last_ping < self.watchdog_interval_s / 2:
            return False
        self._last_ping = now
        return self.watchdog()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
