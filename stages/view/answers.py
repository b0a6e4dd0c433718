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

Clicks and boxes ("click", "box") and combinations of two answers ("combine") are requests of
their own kind, run as a prompt is (a new generation, cancellable, previews, the history,
counted against the page's prompts a second). A click or box refines the answer on display
(its `base`: the page's current step), as `goi select --prompt T --click ...` refines T's.

Every final answer a page is shown becomes one of its *steps*; `undo` and `redo` move along
them (the first step is "nothing"), and a new answer after an undo drops the steps after it.
A page's steps are bounded in bytes (`undo_bytes`, the oldest go first). Answers can be kept
under a name, shared by all pages (`keep`, `forget`), within `history_bytes` of their own
(naming past it is refused, never evicting a name); any two combine (union, intersection,
difference; invert of one), and all of them export as the labels of the scene's PLY.
"""

from __future__ import annotations

import itertools
import threading
import time
import traceback
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from stages.core.errors import GoiError
from stages.core.files import OutputBusy, output_lock
from stages.query.pointing import BoxPrompt, Click
from stages.scene.cameras import Camera
from stages.view.selections import OPS
from stages.view.session import ROUTE_NAMES, Answer, ViewSession, kept
from stages.view.worker import Control, Job, Worker

#: Seconds an answer waits for another goi process that holds the RES index (goi select's
#: --index-wait default) before giving up; the page can cancel it sooner.
INDEX_WAIT_S = 600.0
#: A page's prompts are counted over this many seconds (--prompts-per-s).
RATE_WINDOW_S = 10.0
#: What a page says for a failure that is not the user's (the log has the traceback).
INTERNAL = "the viewer failed on this request (a bug: its log has the details)"
#: An operand of a combination that is the answer on display, not a named one.
SHOWN = "(the answer shown)"
#: The longest name an answer can be kept under.
MAX_NAME = 60
#: A pointed answer's text writes the text of the answer it refines up to this many
#: characters (a chain of clicks would grow it without end).
BASE_TEXT = 100


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
        """The shared history (or the named answers) gained or lost an answer."""

    def clear(self) -> None:
        """Show no answer (an undo back to the first step)."""

    def steps(self, items: list[str], at: int) -> None:
        """The page's steps (each final answer it was shown), and the one on display."""


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
        return f"{self.kind} {_quote(str(self.payload.get('text', '')))}"


@dataclass(frozen=True)
class Shown:
    """An answer as a page shows it: for which request, and whether it is a preview (a step
    before the route's final answer)."""

    request: Request
    answer: Answer
    source: str  # "field" (the field's first answer), "route", "history", "step" (undo, redo)

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
    steps: list[Answer | None] = field(default_factory=lambda: [None])  # [0]: nothing shown
    at: int = 0  # the step on display

    def current(self) -> Answer | None:
        return self.steps[self.at]


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
        undo_bytes: int = 64 << 20,
    ):
        self.session = session
        self.worker = worker
        self.log = log
        self.history = History(history_bytes)
        self.max_exports = max_exports
        self.prompts_per_s = prompts_per_s
        self.undo_bytes = undo_bytes
        self.named_bytes = history_bytes
        self._named: OrderedDict[str, Answer] = OrderedDict()
        self._serial = itertools.count(1)  # a pointed or combined request's own key
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

    def _deliver(self, req: Request, answer: Answer, source: str, step: bool = False) -> bool:
        """Show `answer` for `req` when it is still the page's newest request; `step`: it
        becomes the page's newest step (a final answer)."""
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
            if step:
                self._step(desk, answer)
        return True

    def _step(self, desk: _Desk, answer: Answer) -> None:
        """`answer` as the desk's newest step (the steps after the one on display dropped),
        the oldest dropped past `undo_bytes` (under the desk's lock)."""
        desk.steps = [*desk.steps[: desk.at + 1], answer]
        desk.at = len(desk.steps) - 1
        sizes = [0 if a is None else a.nbytes() for a in desk.steps]
        while sum(sizes) > self.undo_bytes and len(desk.steps) > 1:
            desk.steps.pop(0)
            sizes.pop(0)
            desk.at -= 1
        self._tell_steps(desk)

    @staticmethod
    def _tell_steps(desk: _Desk) -> None:
        desk.display.steps([_step_line(a) for a in desk.steps], desk.at)

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
            self._deliver(req, cached, "history", step=True)
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
            self._deliver(req, k, "route", step=True)
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
        self._deliver(req, ans, "history", step=True)
        return True

    # -- clicks and boxes -------------------------------------------------------------------

    def point(
        self,
        page: Hashable,
        clicks: list[Click],
        boxes: list[BoxPrompt],
        cams: dict[str, Camera],
        granularity: str,
    ) -> Request | None:
        """Clicks or boxes from `page` (at its cameras `cams`), refining the page's answer on
        display; None when refused (no SAM, or a SAM that takes no clicks; an answer still
        refining; too many requests)."""
        kind = "click" if clicks else "box"
        desk = self._desk(page)
        if desk is None:
            return None
        try:
            self.session.check_point(kind)
            if desk.shown is not None and desk.shown.preview:
                raise GoiError(
                    f"{kind}: the answer on display is still refining; wait for it, then "
                    f"{kind} to refine it"
                )
            self._count_prompt(page)
        except GoiError as e:
            self.refuse(page, str(e))
            return None
        base = desk.current()
        what = ", ".join(
            [f"{'+' if c.positive else '-'} click at {c.u:.0f},{c.v:.0f}" for c in clicks]
            + ["box " + ",".join(f"{x:.0f}" for x in b.box) for b in boxes]
        )
        text = what if base is None else f"{_clip(base.prompt.text, BASE_TEXT)} {what}"
        payload = {"text": text, "clicks": [c.text() for c in clicks],
                   "boxes": [b.text() for b in boxes], "granularity": granularity}  # fmt: skip

        def answer(req: Request, control: Control) -> Answer:
            return self.session.point(clicks, boxes, base, cams, granularity, text, control)

        return self.request(page, kind, payload, (kind, next(self._serial)), answer)

    # -- steps ------------------------------------------------------------------------------

    def undo(self, page: Hashable) -> bool:
        """Show the page's step before the one on display."""
        return self._move(page, -1)

    def redo(self, page: Hashable) -> bool:
        """Show the page's step after the one on display (after an undo)."""
        return self._move(page, +1)

    def _move(self, page: Hashable, by: int) -> bool:
        desk = self._desk(page)
        if desk is None:
            return False
        under_way = self.worker.pending(lambda o: o == (page, "answer")) > 0
        with desk.lock:
            on_step = desk.current() is (desk.shown.answer if desk.shown is not None else None)
            if by < 0 and (under_way or not on_step):
                by = 0  # undo a request under way (or its preview): back to the step before it
            if not 0 <= desk.at + by < len(desk.steps):
                what = "undo" if by < 0 else "redo"
                self.refuse(page, f"nothing to {what}")
                return False
            desk.at += by
            desk.generation += 1  # what is under way for the page is dropped
            ans = desk.steps[desk.at]
            self.worker.cancel((page, "answer"))
            if ans is None:
                desk.shown = None
                desk.display.clear()
            else:
                payload = {"text": ans.prompt.text, "route": ans.route}
                desk.shown = Shown(Request(page, desk.generation, ans.kind, payload), ans, "step")
                desk.display.show(desk.shown)
            desk.display.idle()
            self._tell_steps(desk)
        self.log(f"page {page} {'undid' if by < 0 else 'redid'} a step")
        return True

    # -- named answers, combined --------------------------------------------------------------

    def named(self) -> list[tuple[str, Answer]]:
        """The answers kept under a name, in the order they were named."""
        with self._lock:
            return list(self._named.items())

    def keep(self, page: Hashable, name: object) -> bool:
        """Keep the page's answer on display under `name` (replacing the answer of that name)."""
        desk = self._desk(page)
        if desk is None:
            return False
        try:
            n = _check_name(name)
            ans = desk.current()
            if ans is None or (desk.shown is not None and desk.shown.preview):
                raise GoiError("name: there is no final answer on display to keep")
            with self._lock:
                held = sum(a.nbytes() for k, a in self._named.items() if k != n)
                if held + ans.nbytes() > self.named_bytes:
                    raise GoiError(
                        f"name: the named answers would take {(held + ans.nbytes()) / 2**20:.1f} "
                        f"MiB, past --history-mib {self.named_bytes >> 20}; forget one first"
                    )
                self._named[n] = ans
        except GoiError as e:
            self.refuse(page, str(e))
            return False
        self.log(f"page {page} kept {_step_line(ans)} as {_quote(n)}")
        self.history_changed()
        return True

    def forget(self, page: Hashable, name: object) -> bool:
        with self._lock:
            gone = self._named.pop(name, None) if isinstance(name, str) else None
        if gone is None:
            self.refuse(page, "name: no answer is kept under that name")
            return False
        self.history_changed()
        return True

    def combine(self, page: Hashable, op: object, a: object, b: object = None) -> Request | None:
        """The union, intersection or difference of answers `a` and `b`, or the invert of
        `a` (each a name, or SHOWN: the answer on display), as the page's next answer."""
        desk = self._desk(page)
        if desk is None:
            return None
        try:
            if not isinstance(op, str) or op not in OPS:
                raise GoiError(f"combine: the operation is one of {', '.join(OPS)}")
            A = self._operand(desk, a, "A")
            B = None if op == "invert" else self._operand(desk, b, "B")
            self._count_prompt(page)
        except GoiError as e:
            self.refuse(page, str(e))
            return None
        la = a if a != SHOWN else _clip(A.prompt.text, BASE_TEXT)
        if B is None:
            text = f"not ({la})"
        else:
            lb = b if b != SHOWN else _clip(B.prompt.text, BASE_TEXT)
            text = f"({la}) {OPS[op]} ({lb})"

        def answer(req: Request, control: Control) -> Answer:
            return self.session.combine(op, A, B, text)

        payload = {"text": text, "op": op}
        return self.request(page, "combine", payload, ("combine", next(self._serial)), answer)

    def _operand(self, desk: _Desk, name: object, which: str) -> Answer:
        if name == SHOWN:
            ans = desk.current()
            if ans is None or (desk.shown is not None and desk.shown.preview):
                raise GoiError(f"combine: {which} is the answer shown, and there is no final one")
            return ans
        with self._lock:
            got = self._named.get(name) if isinstance(name, str) else None
        if got is None:
            raise GoiError(f"combine: {which} is not one of the named answers")
        return got

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
        owner = self._export_owner(page)
        if owner is None:
            return False
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

    def export_labels(self, page: Hashable) -> bool:
        """The named answers as the labels of the scene's PLY (its own job)."""
        named = self.named()
        if not named:
            self.refuse(page, "labels: keep an answer under a name first")
            return False
        owner = self._export_owner(page)
        if owner is None:
            return False
        desk = self._desk(page)
        assert desk is not None

        def job(control: Control) -> None:
            try:
                path = self.session.export_labels(named)
            except GoiError as e:
                self.log(f"refused an export of the labels: {e}")
                desk.display.exported(f"labels: {e}", True)
                return
            self.log(f"exported the labels of {len(named)} named answers: {path}")
            desk.display.exported(f"wrote {path}", False)

        self.worker.submit(owner, job, Control())
        return True

    def _export_owner(self, page: Hashable) -> tuple | None:
        """A new export's owner (its own job), or None when the page has `max_exports`
        under way (refused)."""
        desk = self._desk(page)
        if desk is None:
            return None
        under_way = self.worker.pending(
            lambda o: isinstance(o, tuple) and o[:2] == (page, "export")
        )
        if under_way >= self.max_exports:
            self.refuse(page, f"{under_way} exports are under way; wait for one to finish")
            return None
        with desk.lock:
            desk.exports += 1
            return (page, "export", desk.exports)

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
    return repr(_clip(text, n))


def _clip(text: str, n: int) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def _step_line(ans: Answer | None) -> str:
    """A step as the page lists it."""
    if ans is None:
        return "nothing selected"
    what = {"text": ROUTE_NAMES.get(ans.route, ans.route), "click": "click", "box": "box",
            "combine": "combined"}.get(ans.kind, ans.kind)  # fmt: skip
    return f"{_clip(ans.prompt.text, 80)} ({what}): {ans.count:,}"


def _check_name(name: object) -> str:
    """A name to keep an answer under: text, printable, 1..MAX_NAME characters."""
    if not isinstance(name, str):
        raise GoiError("name: not text")
    n = name.strip()
    if not n:
        raise GoiError("name: type a name for the answer first")
    if len(n) > MAX_NAME:
        raise GoiError(f"name: {len(n)} characters; at most {MAX_NAME}")
    if not n.isprintable():
        raise GoiError("name: it holds a character that is not printable")
    if n == SHOWN:
        raise GoiError(f"name: {SHOWN} is the answer on display; choose another name")
    return n
