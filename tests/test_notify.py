"""sd_notify on a real AF_UNIX datagram socket, as systemd listens for it."""

from __future__ import annotations

import socket

from vs2t_edge.runtime.notify import Notifier


def test_messages_arrive_on_the_notify_socket(tmp_path, monkeypatch):
    path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(path)
    server.settimeout(2)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    n = Notifier()
    assert n.watchdog_s == 2.0
    n.ready("bundle verified")
    n.status("sorting")
    n.status("sorting")  # unchanged STATUS is not sent again
    n.watchdog()
    n.stopping("SIGTERM")
    got = [server.recv(4096).decode() for _ in range(4)]
    assert got == ["READY=1\nSTATUS=bundle verified", "STATUS=sorting", "WATCHDOG=1", "STOPPING=1\nSTATUS=SIGTERM"]
    server.close()


def test_abstract_socket_and_no_socket(monkeypatch):
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind("\0vs2t-notify-test")
    server.settimeout(2)
    Notifier(address="@vs2t-notify-test").watchdog()
    assert server.recv(100) == b"WATCHDOG=1"
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    quiet = Notifier()
    quiet.ready()
    assert list(quiet.sent) == ["READY=1"]  # recorded, nothing sent, no error


def test_watchdog_due_at_a_tenth_of_the_interval(monkeypatch):
    # a half let a ping due just before a long step arrive after the watchdog fired (issue 17)
    t = [0.0]
    monkeypatch.setenv("WATCHDOG_USEC", "10000000")
    n = Notifier(address="", clock=lambda: t[0])
    n.watchdog()
    t[0] = 0.99
    assert not n.watchdog_due()
    t[0] = 1.0
    assert n.watchdog_due()


def test_the_record_of_messages_is_bounded():
    from vs2t_edge.runtime.notify import KEEP_MESSAGES

    n = Notifier(address="")
    for i in range(KEEP_MESSAGES * 3):
        n.status(f"item {i}")
    assert len(n.sent) == KEEP_MESSAGES and n.n_sent == KEEP_MESSAGES * 3
    assert n.sent[-1] == f"STATUS=item {KEEP_MESSAGES * 3 - 1}"  # the newest are kept
