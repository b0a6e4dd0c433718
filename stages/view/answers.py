"""The answer protocol of `goi view`, without a browser: what a page asks, what it is shown and
in which order, what is kept, and what is cancelled.

A page's request (`Request`) carries its kind ("text": a prompt on a route; other kinds, such
as a click, a box or a combination of two answers, are requests of their own kind with their
own payload) and the page's *generation*: every request a page makes (a prompt, a pick from the
history) starts a new generation, and everything that comes back for an older one (a partial
answer, a progress step, the field's first answer, a final answer, a wait for a lock) is
dropped, whether the job noticed its cancellation yet or not. So a page shows only its own
newest answer; a cancelled answer's late partial never lingers as "(refining...)".

A text request is answered in steps, each delivered as a `Shown` (the answer and whether it is
a preview): the field's answer first when it is a fitted plane (the prompt's cached OSH; the
fixed threshold is a guess that lights up half a room, so it is shown only where it is the
route asked for), then the route's partial answers (previews, labelled as such), then its
final answer, which enters the history. Each page has one answer job at a time (stages.view
.worker: a new request replaces it); each export is a job of its own, never cancelled by
another; a page has at most `max_exports` of them under way.

The history is shared by all pages, keyed by (kind, prompt, route), and bounded in bytes: a
final answer is kept without its per-view evidence arrays (`session.kept`: what it shows and
exports, bit for bit), and the oldest answers go when the history passes `history_bytes`.

A lifted answer that must index a view while another goi process writes the RES index waits
for that process with the machine's cores free (the worker's gate released), says so in the
page, and stops when the page asks something else; an index that another process replaced is
read again (stages.view.session).
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from stages.core.errors import GoiError
from stages.core.files import OutputBusy, output_lock
from stages.view.session import ROUTE_NAMES, Answer, ViewSession, kept
from stages.view.worker import Control, Job, Worker

#: Seconds an answer waits for another goi process that holds the RES index (goi select's
#: --index-wait default) before giving up; the page can cancel it sooner.
INDEX_WAIT_S = 600.0
#: A page's prompts are counted over this many seconds (--prompts-per-s).
RATE_WINDOW_S = 10.0
#: What a page says for a failure that is not the user's (the log has the traceback).
INTERNAL = "the viewer failed on this request (a bug: its log has the details)"


class Display(Protocol):
    """What the protocol tells one page (the browser page draws it; the tests record it).
    Called from the worker thread and the page's own threads, one call at a time per page."""

    def show(self, shown: Shown) -> None:
        """Draw an answer (a preview or a final one)."""

    def progress(self, done: int, total: int, what: str) -> None:
        """The running request has done `done` of `total` steps."""

    def note(self, text: str) -> None:
        """A line about the running request (asking, waiting for another process)."""

    def failed(self, message: str) -> None:
        """The request (or a value the page sent) was refused or failed: one line."""

    def idle(self) -> None:
        """Nothing of this page's is under way any more (hide the progress)."""

    def exported(self, message: str, error: bool) -> None:
        """An export finished (or failed): one line."""

    def history_changed(self) -> None:
        """The shared history gained or lost an answer."""


@dataclass(frozen=True)
class Request:
    """One request of a page: its kind, what it asks, and the page's generation then."""

    page: Hashable
    generation: int
    kind: str  # "text" (a prompt); later kinds add their own
    payload: Mapping[str, Any]

    def describe(self) -> str:
        if self.kind == "text":
            return f"{_quote(self.payload['text'])} ({ROUTE_NAMES[self.payload['route']]})"
        return self.kind


@dataclass(frozen=True)
class Shown:
    """An answer as a page shows it: for which request, and whether it is a preview (a step
    before the route's final answer)."""

    request: Request
    answer: Answer
    source: str  # "field" (the field's first answer), "route", "history"

    @property
    def preview(self) -> bool:
        return not self.answer.final or self.source == "field"


@dataclass
class _Desk:
    """One page's side of the protocol."""

    display: Display
    generation: int = 0
    shown: Shown | None = None
    lock: threading.RLock = field(default_factory=threading.RLock)
    exports: int = 0  # exports asked so far (each its own job)
    asked: deque[float] = field(default_factory=deque)  # when it asked, within RATE_WINDOW_S


class History:
    """Final answers, shared by all pages, keyed by (kind, prompt, route), in bytes bounded."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._answers: OrderedDict[tuple, tuple[Answer, int]] = OrderedDict()
        self._lock = threading.Lock()

    def add(self, ans: Answer) -> Answer:
        """Keep `ans` (as `kept` keeps it); returns the kept answer."""
        k = kept(ans)
        with self._lock:
            self._answers.pop(k.key, None)
            self._answers[k.key] = (k, k.nbytes())
            total = sum(n for _, n in self._answers.values())
            while total > self.max_bytes and len(self._answers) > 1:
                _, (_, n) = self._answers.popitem(last=False)
                total -= n
        return k

    def get(self, key: tuple) -> Answer | None:
        with self._lock:
            entry = self._answers.get(key)
            return entry[0] if entry else None

    def answers(self) -> list[Answer]:
        with self._lock:
            return [a for a, _ in self._answers.values()]

    def nbytes(self) -> int:
        with self._lock:
            return sum(n for _, n in self._answers.values())


class Answers:
    """The protocol (see the module doc): pages open and close, ask, pick, export."""

    def __init__(
        self,
        session: ViewSession,
        worker: Worker,
        log: Callable[[str], None] = lambda message: None,
        history_bytes: int = 128 << 20,
        max_exports: int = 4,
        prompts_per_s: float = 2.0,
    ):
        self.session = session
        self.worker = worker
        self.log = log
        self.history = History(history_bytes)
        self.max_exports = max_exports
        self.prompts_per_s = prompts_per_s
        self._desks: dict[Hashable, _Desk] = {}
        self._lock = threading.Lock()

    # -- pages ------------------------------------------------------------------------------

    def open(self, page: Hashable, display: Display) -> None:
        with self._lock:
            self._desks[page] = _Desk(display)

    def close(self, page: Hashable) -> None:
        with self._lock:
            desk = self._desks.pop(page, None)
        if desk is not None:
            with desk.lock:
                desk.generation += 1  # whatever is still under way for it is dropped
        self.worker.cancel((page, "answer"))

    def shown(self, page: Hashable) -> Shown | None:
        desk = self._desk(page)
        return desk.shown if desk else None

    def _desk(self, page: Hashable) -> _Desk | None:
        with self._lock:
            return self._desks.get(page)

    def _new_request(self, page: Hashable, kind: str, payload: Mapping[str, Any]) -> Request:
        desk = self._desk(page)
        if desk is None:
            raise GoiError("the page is closed")
        with desk.lock:
            desk.generation += 1
            return Request(page, desk.generation, kind, payload)

    def _current(self, req: Request) -> _Desk | None:
        """The request's page when the request is still its newest (to be called, and the
        page told, under the desk's lock)."""
        desk = self._desk(req.page)
        if desk is None or desk.generation != req.generation:
            return None
        return desk

    # -- telling a page, for a request that is still its newest ------------------------------

    def _deliver(self, req: Request, answer: Answer, source: str) -> bool:
        desk = self._desk(req.page)
        if desk is None:
            return False
        with desk.lock:
            if self._current(req) is None:
                return False
            desk.shown = Shown(req, answer, source)
            desk.display.show(desk.shown)
            if answer.final and source != "field":
                desk.display.idle()
        return True

    def _tell(self, req: Request, what: str, *args: Any) -> None:
        desk = self._desk(req.page)
        if desk is None:
            return
        with desk.lock:
            if self._current(req) is not None:
                getattr(desk.display, what)(*args)

    def refuse(self, page: Hashable, message: str) -> None:
        """A value a page sent is refused: one line in that page, one in the log."""
        desk = self._desk(page)
        self.log(f"refused a value from page {page}: {message}")
        if desk is not None:
            with desk.lock:
                desk.display.failed(message)

    # -- asking -----------------------------------------------------------------------------

    def ask(self, page: Hashable, text: str, route: str) -> Request | None:
        """A prompt on a route, from `page` (see the module doc); None when refused."""
        s = self.session
        try:
            prompt = s.check_prompt(text)
            why = s.routes().get(route, f"unknown route {route!r}")
            if why is not None:
                raise GoiError(f"route {route}: {why}")
            self._count_prompt(page)
        except GoiError as e:
            self.refuse(page, str(e))
            return None
        payload = {"text": prompt, "route": route}
        return self.request(page, "text", payload, ("text", prompt, route), self._answer_text)

    def request(
        self,
        page: Hashable,
        kind: str,
        payload: Mapping[str, Any],
        key: tuple,
        answer: Callable[[Request, Control], Answer],
    ) -> Request:
        """A checked request of any kind (a prompt; later a click, a box, a combination of
        answers): a new generation of the page; the answer from the history under `key` when
        it is there, else `answer(request, control)` on the worker (it may deliver previews),
        waited for patiently, kept in the history and shown."""
        req = self._new_request(page, kind, payload)
        self.log(f"page {page} asks {req.describe()}")
        cached = self.history.get(key)
        if cached is not None:
            self.worker.cancel((page, "answer"))
            self._deliver(req, cached, "history")
            return req
        self._tell(req, "note", f"answering {req.describe()}...")
        self._tell(req, "progress", 0, 1, "")
        control = Control()
        control.partial = lambda a: self._deliver(req, a, "route")
        control.progress = lambda done, total, what: self._tell(req, "progress", done, total, what)

        def job(control: Control) -> None:
            t0 = time.perf_counter()
            ans = self._patiently(req, control, lambda: answer(req, control))
            control.check()
            k = self.history.add(ans)
            self._deliver(req, k, "route")
            self.log(
                f"answered {req.describe()}: {k.count:,} Gaussians ({k.label}) in "
                f"{time.perf_counter() - t0:.2f} s"
            )
            self.history_changed()

        self.worker.submit((page, "answer"), job, control)
        return req

    def _count_prompt(self, page: Hashable) -> None:
        desk = self._desk(page)
        if desk is None:
            raise GoiError("the page is closed")
        most = max(1, int(self.prompts_per_s * RATE_WINDOW_S))
        now = time.monotonic()
        with desk.lock:
            while desk.asked and now - desk.asked[0] > RATE_WINDOW_S:
                desk.asked.popleft()
            if len(desk.asked) >= most:
                raise GoiError(
                    f"prompt: {most} prompts in {RATE_WINDOW_S:.0f} s from this page; wait a "
                    f"moment (--prompts-per-s {self.prompts_per_s:g})"
                )
            desk.asked.append(now)

    def pick(self, page: Hashable, key: tuple) -> bool:
        """Show a history entry (again, if it is on display already)."""
        ans = self.history.get(key)
        if ans is None:
            self.refuse(page, "that answer is no longer in the history; ask it again")
            return False
        req = self._new_request(page, ans.kind, {"text": ans.prompt.text, "route": ans.route})
        self.worker.cancel((page, "answer"))
        self._deliver(req, ans, "history")
        return True

    def _answer_text(self, req: Request, control: Control) -> Answer:
        s = self.session
        text, route = req.payload["text"], req.payload["route"]
        if route not in ("threshold", "lifted_fieldless"):
            first = s.field_answer(text)
            # only a fitted plane is worth showing first (the fixed threshold is the answer of
            # the threshold route, and a guess anywhere else)
            if first is not None and first.route == "osh":
                label = f"the field's cached OSH, first: {first.label}"
                self._deliver(req, _preview(first, label), "field")
        return s.answer(text, route, control)

    def _patiently(self, req: Request, control: Control, compute: Callable[[], Answer]) -> Answer:
        """`compute`, waiting (cancellably, the gate released) while another goi process
        holds the RES index, and reading the index again when it changed underneath."""
        s = self.session
        deadline = time.monotonic() + INDEX_WAIT_S
        reread = False
        while True:
            try:
                return compute()
            except OutputBusy as e:
                path = s.index_lock_path()
                assert path is not None
                busy = str(e).split("; ")[0]
                self._tell(req, "note", f"{busy}: waiting for it (ask something else to stop)")
                self.log(f"{busy}: {req.describe()} waits for it")
                with self.worker.gate.released():
                    while True:
                        control.check()
                        try:
                            with output_lock(path, "--res-index"):
                                break  # it is free: answer again (the views it added count)
                        except OutputBusy:
                            pass
                        if time.monotonic() > deadline:
                            raise GoiError(f"{e} (waited {INDEX_WAIT_S:.0f} s)") from None
                        control.cancelled.wait(0.25)
                self._tell(req, "note", f"answering {req.describe()}...")
            except GoiError as e:
                if reread or "changed while it was read" not in str(e):
                    raise
                reread = True  # replaced while this answer read it: once more, read anew
                s.reopen_index()

    def history_changed(self) -> None:
        with self._lock:
            desks = list(self._desks.values())
        for d in desks:
            d.display.history_changed()

    # -- exports ----------------------------------------------------------------------------

    def export(self, page: Hashable, what: str, color: str) -> bool:
        """Export the page's answer on display (its own job, never cancelled by another)."""
        desk = self._desk(page)
        if desk is None:
            return False
        shown = desk.shown
        if shown is None or shown.preview:
            self.refuse(page, "ask a prompt and wait for its final answer first")
            return False
        under_way = self.worker.pending(
            lambda o: isinstance(o, tuple) and o[:2] == (page, "export")
        )
        if under_way >= self.max_exports:
            self.refuse(page, f"{under_way} exports are under way; wait for one to finish")
            return False
        with desk.lock:
            desk.exports += 1
            owner = (page, "export", desk.exports)
        ans = shown.answer
        where = f"{_quote(ans.prompt.text)} ({ROUTE_NAMES[ans.route]})"

        def job(control: Control) -> None:
            try:
                files = self.session.export(ans, what, color)
            except GoiError as e:
                self.log(f"refused an export of {where} ({what}): {e}")
                desk.display.exported(f"{what} of {where}: {e}", True)
                return
            out = files[0] if len(files) == 1 else f"{files[0].parent}/ ({len(files)} files)"
            self.log(f"exported {what} of {where}: {out}")
            desk.display.exported(f"wrote {out}", False)

        self.worker.submit(owner, job, Control())
        return True

    # -- failures ---------------------------------------------------------------------------

    def failed(self, job: Job, e: BaseException) -> None:
        """A job raised (the worker's on_error): a GoiError is the page's one line; anything
        else is a bug, logged with its traceback, and the page says so without details."""
        page = job.owner[0] if isinstance(job.owner, tuple) else job.owner
        if isinstance(e, GoiError):
            message = str(e)
            self.log(f"refused a request of page {page}: {message}")
        else:
            self.log(f"a request of page {page} failed: {type(e).__name__}: {str(e)[:200]}")
            self.log("".join(traceback.format_exception(e)).rstrip())
            message = INTERNAL
        desk = self._desk(page)
        if desk is None:
            return
        with desk.lock:
            if isinstance(job.owner, tuple) and job.owner[1] == "export":
                desk.display.exported(message, True)
            elif not job.control.cancelled.is_set():
                desk.display.failed(message)
                desk.display.idle()


def _preview(ans: Answer, label: str) -> Answer:
    return Answer(ans.prompt, ans.route, ans.selected, label, False, ans.plane,
                  seconds=ans.seconds)  # fmt: skip


def _quote(text: str, n: int = 80) -> str:
    return repr(text if len(text) <= n else text[: n - 3] + "...")
