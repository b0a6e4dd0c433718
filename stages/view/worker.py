"""One worker for every answer, and a gate that lets interactive renders go first.

Answers run one at a time on one thread: goi's kernels already use every core, so two answers
at once would only share them. Every job has an owner (a page's answer, one export); an owner
has at most one job waiting: a new job of the same owner replaces the waiting one and cancels
the running one (it stops at its next step), so a flood of prompts from a page costs one job,
not a queue of cancelled ones. Owners are served in the order they asked. The mask at a page's
camera is rendered on the caller's thread through the same gate: the running answer pauses
between two of its steps to let it in, so a page never waits for a whole answer to see its
mask; and a job that must wait for something else (another process's lock) lets the gate go
while it waits (`Gate.released`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any


class Cancelled(Exception):
    """The job was superseded (a new request from its owner) or the viewer stopped."""


@dataclass
class Control:
    """How a running job talks back: its partial answers and progress, and whether it should
    stop. `pause` is called between steps (the worker lets an interactive render in)."""

    cancelled: threading.Event = field(default_factory=threading.Event)
    partial: Callable[[Any], Any] = lambda a: None  # a partial answer (stages.view.session)
    progress: Callable[[int, int, str], None] = lambda done, total, what: None
    pause: Callable[[], None] = lambda: None
    #: Seconds between two partial answers of a lifted route (each costs a vote).
    partial_every: float = 0.5

    def check(self) -> None:
        if self.cancelled.is_set():
            raise Cancelled()


class Gate:
    """A lock on the machine's cores with priority for interactive work: `pause()` (called by
    the worker between steps, holding the gate) hands it to waiting `urgent()` callers first."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cond = threading.Condition()
        self._waiting = 0

    @contextmanager
    def urgent(self) -> Iterator[None]:
        with self._cond:
            self._waiting += 1
        self._lock.acquire()
        with self._cond:
            self._waiting -= 1
            self._cond.notify_all()
        try:
            yield
        finally:
            self._lock.release()

    @contextmanager
    def background(self) -> Iterator[None]:
        with self._lock:
            yield

    @contextmanager
    def released(self) -> Iterator[None]:
        """Inside a background job: let the gate go for a while (a wait on something else)."""
        self._lock.release()
        try:
            yield
        finally:
            self._lock.acquire()

    def pause(self) -> None:
        """Between two steps of a background job: let every waiting urgent caller in."""
        with self._cond:
            if not self._waiting:
                return
        self._lock.release()
        try:
            with self._cond:
                self._cond.wait_for(lambda: self._waiting == 0, timeout=30)
        finally:
            self._lock.acquire()


@dataclass
class Job:
    owner: Hashable  # who asked, and for what: (page id, "answer"), (page id, "export", n)
    run: Callable[[Control], None]
    control: Control = field(default_factory=Control)
    done: threading.Event = field(default_factory=threading.Event)

    def cancel(self) -> None:
        self.control.cancelled.set()


class Worker:
    """The one thread that runs jobs (see the module doc)."""

    def __init__(self, on_error: Callable[[Job, BaseException], None]) -> None:
        self.gate = Gate()
        self._waiting: OrderedDict[Hashable, Job] = OrderedDict()  # at most one per owner
        self._running: Job | None = None
        self._cond = threading.Condition()
        self._stopped = False
        self._on_error = on_error
        self._thread = threading.Thread(target=self._loop, name="goi-view-worker", daemon=True)
        self._thread.start()

    def submit(self, owner: Hashable, run: Callable[[Control], None], control: Control) -> Job:
        """Queue a job for `owner`, replacing its waiting job and cancelling its running one."""
        job = Job(owner, run, control)
        control.pause = self.gate.pause
        with self._cond:
            if self._stopped:
                job.cancel()
                job.done.set()
                return job
            self._cancel(owner)
            self._waiting[owner] = job
            self._cond.notify_all()
        return job

    def cancel(self, owner: Hashable) -> None:
        with self._cond:
            self._cancel(owner)

    def _cancel(self, owner: Hashable) -> None:
        old = self._waiting.pop(owner, None)
        if old is not None:
            old.cancel()
            old.done.set()
        if self._running is not None and self._running.owner == owner:
            self._running.cancel()

    def pending(self, match: Callable[[Hashable], bool]) -> int:
        """How many jobs of the owners `match` names are waiting or running, and not
        cancelled (a cancelled job stops at its next step)."""
        with self._cond:
            jobs = [*self._waiting.values(), *([self._running] if self._running else [])]
            return sum(1 for j in jobs if match(j.owner) and not j.control.cancelled.is_set())

    def busy(self) -> bool:
        with self._cond:
            return bool(self._waiting) or self._running is not None

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            for job in self._waiting.values():
                job.cancel()
                job.done.set()
            self._waiting.clear()
            if self._running is not None:
                self._running.cancel()
            self._cond.notify_all()
        self._thread.join(timeout=30)

    def _loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stopped or bool(self._waiting))
                if self._stopped:
                    return
                _, job = self._waiting.popitem(last=False)
                self._running = job
            try:
                if not job.control.cancelled.is_set():
                    with self.gate.background():
                        job.run(job.control)
            except Cancelled:
                pass
            except BaseException as e:  # reported to the page; the worker carries on
                self._on_error(job, e)
            finally:
                with self._cond:
                    self._running = None
                job.done.set()
