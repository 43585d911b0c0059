"""Progress bars: tqdm on a terminal, plain periodic lines in a log, silent with PRML2_NO_PROGRESS=1."""

from __future__ import annotations

import io

import pytest

from prml2_edge import progress
from prml2_edge.progress import Progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_without_a_terminal_it_prints_whole_lines_and_no_carriage_return(monkeypatch):
    monkeypatch.delenv("PRML2_NO_PROGRESS", raising=False)
    monkeypatch.setattr(progress, "LINE_INTERVAL_S", 0.0)  # a line on every update
    log = io.StringIO()
    with Progress(50, desc="epoch 1/2 pretrain", unit="batch", stream=log) as bar:
        for i in range(50):
            bar.update()
            bar.set_postfix(f"loss {i}")
    text = log.getvalue()
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert len(lines) > 10 and all(line.startswith("epoch 1/2 pretrain") for line in lines)
    assert "50/50" in lines[-1] and "loss 49" in lines[-1]
    assert bar.n == 50 and bar.total == 50


def test_lines_are_periodic_not_per_update(monkeypatch):
    monkeypatch.delenv("PRML2_NO_PROGRESS", raising=False)
    log = io.StringIO()  # default interval (30 s): the first line, then only the final one
    with Progress(10_000, desc="replay", unit="frames", stream=log) as bar:
        for _ in range(10_000):
            bar.update()
    lines = log.getvalue().splitlines()
    assert len(lines) == 2 and "10000/10000" in lines[-1]


def test_on_a_terminal_tqdm_redraws_in_place(monkeypatch):
    monkeypatch.delenv("PRML2_NO_PROGRESS", raising=False)
    tty = _Tty()
    with Progress(None, desc="replay", unit="frames", stream=tty) as bar:
        bar.update(7)
    assert "\r" in tty.getvalue() and "7frames" in tty.getvalue()


@pytest.mark.parametrize("stream", [io.StringIO, _Tty])
def test_prml2_no_progress_silences_it(monkeypatch, stream):
    monkeypatch.setenv("PRML2_NO_PROGRESS", "1")
    out = stream()
    with Progress(5, desc="x", stream=out) as bar:
        bar.update(5)
    assert out.getvalue() == ""
    quiet = io.StringIO()
    monkeypatch.delenv("PRML2_NO_PROGRESS")
    with Progress(5, stream=quiet, enabled=False) as bar:
        bar.update(5)
    assert quiet.getvalue() == ""
