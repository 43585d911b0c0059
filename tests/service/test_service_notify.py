"""sd_notify protocol against a datagram socket the test opens (what systemd does)."""

import os
import socket

import pytest

from prml2_edge.service.notify import SystemdNotifier


@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield path, sock
    sock.close()


def test_ready_status_watchdog_stopping(notify_socket):
    path, sock = notify_socket
    clock = [100.0]
    n = SystemdNotifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "2000000",
                         "WATCHDOG_PID": str(os.getpid())}, clock=lambda: clock[0])
    assert n.enabled and n.watchdog_interval_s == 2.0
    assert n.ready("replaying")
    assert sock.recv(4096).decode() == "READY=1\nSTATUS=replaying"
    assert n.maybe_ping()
    assert sock.recv(4096) == b"WATCHDOG=1"
    clock[0] += 0.5
    assert not n.maybe_ping()  # less than half the interval since the last ping
    clock[0] += 0.6
    assert n.maybe_ping()
    assert sock.recv(4096) == b"WATCHDOG=1"
    assert n.stopping()
    assert sock.recv(4096) == b"STOPPING=1"
    n.close()


def test_abstract_socket_address(tmp_path):
    name = f"prml2-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        n = SystemdNotifier({"NOTIFY_SOCKET": "@" + name})
        assert n.status("ok")
        assert sock.recv(100) == b"STATUS=ok"
    finally:
        sock.close()


def test_without_systemd_everything_is_a_no_op():
    n = SystemdNotifier({})
    assert not n.enabled and not n.ready() and not n.maybe_ping()


def test_watchdog_for_another_pid_is_ignored_and_send_failures_are_counted(tmp_path):
    n = SystemdNotifier({"NOTIFY_SOCKET": str(tmp_path / "absent.sock"), "WATCHDOG_USEC": "1000",
                         "WATCHDOG_PID": str(os.getpid() + 1)})
    assert n.watchdog_interval_s is None
    assert not n.ready()  # nobody listening: counted, not raised
    assert n.send_failures == 1
