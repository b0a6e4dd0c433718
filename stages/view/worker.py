"""One worker for every answer, and a gate that lets interactive renders go first.

Answers run one at a time, in the order they were asked, on one thread: goi's kernels already
use every core, so two answers at once would only share them. Each page (browser tab) owns its
jobs; a new prompt from a page cancels that page's unfinished job (it stops at its next step),
while other pages' jobs run to their end. The mask at the browser's camera is rendered on the
caller's thread through the same gate: the running answer pauses between two of its steps to
let it in, so the page never waits for a whole answer to see its mask.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from stages.view.session import Cancelled, Control


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
    owner: Hashable  # the page that asked (and what for)
    run: Callable[[Control], None]
    control: Control = field(default_factory=Control)
    done: threading.Event = field(default_factory=threading.Event)

    def cancel(self) -> None:
        self.control.cancelled.set()


class Worker:
    """The one thread that runs answers (see the module doc)."""

    def __init__(self, on_error: Callable[[Job, BaseException], None]) -> None:
        self.gate = Gate()
        self._queue: queue.Queue[Job | None] = queue.Queue()
        self._open: list[Job] = []
        self._lock = threading.Lock()
        self._on_error = on_error
        self._thread = threading.Thread(target=self._loop, name="goi-view-worker", daemon=True)
        self._thread.start()

    def submit(self, owner: Hashable, run: Callable[[Control], None], control: Control) -> Job:
        """Queue an answer for page `owner`, cancelling that page's unfinished ones."""
        job = Job(owner, run, control)
        control.pause = self.gate.pause
        with self._lock:
            for old in self._open:
                if old.owner == owner:
                    old.cancel()
            self._open.append(job)
        self._queue.put(job)
        return job

    def cancel(self, owner: Hashable) -> None:
        with self._lock:
            for job in self._open:
                if job.owner == owner:
                    job.cancel()

    def busy(self) -> bool:
        with self._lock:
            return bool(self._open)

    def stop(self) -> None:
        with self._lock:
            for job in self._open:
                job.cancel()
        self._queue.put(None)
        self._thread.join(timeout=30)

    def _loop(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            try:
                if not job.control.cancelled.is_set():
                    with self.gate.background():
                        job.run(job.control)
            except Cancelled:
                pass
            except BaseException as e:  # reported to the page; the worker carries on
                self._on_error(job, e)
            finally:
                with self._lock:
                    self._open.remove(job)
                job.done.set()
