"""A Ctrl-C swallowed on its way (Python only prints a KeyboardInterrupt raised in a weakref
callback or a __del__) still stops the next loop that reports progress
(stages/core/interrupts.py)."""

from __future__ import annotations

import contextlib
import signal
import threading

import pytest

from stages.core.interrupts import check, stoppable
from stages.core.report import SILENT, Lines


@pytest.fixture(autouse=True)
def python_s_handler():
    """Python's own SIGINT handler, as in a terminal: a suite started in the background (CI's)
    inherits SIGINT ignored, and goi then leaves it ignored."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _swallowed_ctrl_c() -> None:
    try:
        signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        pass  # as in a weakref callback: printed, and the run goes on


BAR = Lines(bar=lambda items, label, length, show: contextlib.nullcontext(items))


@pytest.mark.parametrize(
    "report", [SILENT, Lines(write=lambda m: None), BAR], ids=["silent", "lines", "bar"]
)
def test_a_swallowed_ctrl_c_stops_the_next_progress_loop(report):
    done = []
    with stoppable():
        _swallowed_ctrl_c()
        with pytest.raises(KeyboardInterrupt):
            for i in report.progress(range(5), "fit", length=5):
                done.append(i)
    assert done == []


def test_the_interrupt_is_forgotten_after_the_command_and_python_s_handler_is_back():
    with stoppable():
        _swallowed_ctrl_c()
    check()  # nothing pending outside the command
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert list(SILENT.progress(range(3), "x")) == [0, 1, 2]


def test_a_process_that_ignores_sigint_keeps_ignoring_it():
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with stoppable():
            signal.raise_signal(signal.SIGINT)  # ignored: nothing raised, nothing recorded
            check()
    finally:
        signal.signal(signal.SIGINT, before)


def test_outside_the_main_thread_nothing_is_installed():
    seen = []

    def run() -> None:
        with stoppable():
            seen.append(signal.getsignal(signal.SIGINT))

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert seen == [signal.default_int_handler]
