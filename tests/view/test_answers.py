"""The answer protocol without a browser (stages.view.answers): a page shows only its own
newest answer, whatever a superseded job still sends; a history entry picked again is shown
again; every export is its own job; a wait for another process's index lock lets the cores
go, is shown in the page and can be cancelled; the history is bounded in bytes.

Most tests script the session's answers step by step (`Scripted`: the protocol is the thing
under test, and the order of events must be forced, not hoped for); the last ones run the
real session on a RES index that another process replaces."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from stages.core.errors import GoiError
from stages.core.files import output_lock
from stages.query.prompts import Prompt, check_prompt
from stages.view.answers import SHOWN, Answers, Shown
from stages.view.session import Answer
from stages.view.worker import Control, Worker
from tests.query.test_res_index import photographed  # noqa: F401  (a scene with photos)
from tests.view.served import wait_for

ROUTE = "lifted_fieldless"
G = 1000


def answer_of(text: str, final: bool = True, n: int = 10) -> Answer:
    sel = np.zeros(G, bool)
    sel[hash(text) % (G - n) :][:n] = True
    return Answer(Prompt(text), ROUTE, sel, "scripted", final)


class Scripted:
    """A session whose answers the test writes: `plan[text](control) -> Answer`."""

    def __init__(self) -> None:
        self.plan: dict = {}
        self.lock_path = None
        self.exported: list[tuple[str, str]] = []
        self.export_gate = threading.Event()
        self.export_gate.set()
        self.boxes_only = False
        self.pointed: list[tuple] = []

    def check_prompt(self, text: str) -> str:
        return check_prompt(text, "prompt")

    def routes(self) -> dict:
        return {ROUTE: None, "threshold": None, "osh": None, "lifted": None}

    def field_answer(self, text: str):  # noqa: ANN201
        return None

    def answer(self, text: str, route: str, control: Control) -> Answer:
        return self.plan.get(text, lambda c: answer_of(text))(control)

    def check_point(self, kind: str) -> None:
        if kind == "click" and self.boxes_only:
            raise GoiError("click: the bundle's SAM takes boxes only")

    def point(self, clicks, boxes, base, cams, granularity, text, control):  # noqa: ANN001, ANN201
        """A click answers its pixel's column as a band of 10 Gaussians, added to the base."""
        self.pointed.append((clicks, boxes, base, granularity))
        sel = np.zeros(G, bool) if base is None else base.selected.copy()
        for c in clicks:
            band = slice(int(c.u), int(c.u) + 10)
            if c.positive:
                sel[band] = True
            else:
                sel[band] = False
        kind = "click" if clicks else "box"
        return Answer(Prompt(text), "pointed", sel, "scripted", True, kind=kind)

    def combine(self, op, a, b, text):  # noqa: ANN001, ANN201
        from stages.view.selections import combine

        sel, score = combine(op, a.selected, None if b is None else b.selected)
        return Answer(Prompt(text), "combined", sel, "scripted", True, kind="combine", score=score)

    def index_lock_path(self):  # noqa: ANN201
        return self.lock_path

    def reopen_index(self) -> None:
        pass

    def export(self, ans: Answer, what: str, color: str) -> list:
        self.export_gate.wait()
        self.exported.append((ans.prompt.text, what))
        return [f"out/{ans.prompt.name}/{what}"]


class Recorder:
    """A page: what the protocol told it, in order."""

    def __init__(self) -> None:
        self.events: list[tuple] = []
        self.lock = threading.Lock()

    def _add(self, *e: object) -> None:
        with self.lock:
            self.events.append(e)

    def show(self, shown: Shown) -> None:
        self._add("show", shown.answer.prompt.text, shown.preview, shown.source)

    def progress(self, done: int, total: int, what: str) -> None:
        self._add("progress", done, total)

    def note(self, text: str) -> None:
        self._add("note", text)

    def failed(self, message: str) -> None:
        self._add("failed", message)

    def idle(self) -> None:
        self._add("idle")

    def exported(self, message: str, error: bool) -> None:
        self._add("exported", message, error)

    def history_changed(self) -> None:
        self._add("history")

    def clear(self) -> None:
        self._add("clear")

    def steps(self, items: list[str], at: int) -> None:
        self._add("steps", tuple(items), at)

    def last_steps(self) -> tuple:
        with self.lock:
            return [e[1:] for e in self.events if e[0] == "steps"][-1]

    def shows(self) -> list[tuple]:
        with self.lock:
            return [e[1:] for e in self.events if e[0] == "show"]

    def has(self, kind: str, text: str = "") -> bool:
        with self.lock:
            return any(e[0] == kind and text in str(e[1:]) for e in self.events)


@pytest.fixture
def protocol():
    session = Scripted()
    box: list[Answers] = []
    worker = Worker(lambda job, e: box[0].failed(job, e))
    answers = Answers(session, worker)  # type: ignore[arg-type]
    box.append(answers)
    page = Recorder()
    answers.open(1, page)
    yield session, answers, page
    worker.stop()


def test_a_superseded_answers_late_partial_and_final_are_never_shown(protocol):
    session, answers, page = protocol
    started, release = threading.Event(), threading.Event()

    def slow(control: Control) -> Answer:
        started.set()
        release.wait()
        control.partial(answer_of("old", final=False))  # after the page asked again
        return answer_of("old")  # (a job that does not look at its cancellation)

    session.plan["old"] = slow
    answers.ask(1, "old", ROUTE)
    assert started.wait(30)
    answers.ask(1, "new", ROUTE)
    release.set()
    wait_for(lambda: ("new", False, "route") in page.shows(), "the new answer")
    wait_for(lambda: not answers.worker.busy(), "the worker idle")
    assert [s for s in page.shows() if s[0] == "old"] == []
    assert answers.shown(1).answer.prompt.text == "new"
    assert [e[0] for e in page.events[-3:]] == ["idle", "steps", "history"]  # the bar hidden


def test_a_page_picks_a_history_entry_again_and_sees_it_again(protocol):
    _, answers, page = protocol
    answers.ask(1, "a chair", ROUTE)
    wait_for(lambda: ("a chair", False, "route") in page.shows(), "the answer")
    answers.ask(1, "a lamp", ROUTE)
    wait_for(lambda: ("a lamp", False, "route") in page.shows(), "the second answer")
    key = ("text", "a chair", ROUTE)
    assert answers.pick(1, key) and answers.pick(1, key)  # the same entry twice
    assert page.shows()[-2:] == [("a chair", False, "history")] * 2
    # asked again, an answer comes from the history at once, on a request of its own
    answers.ask(1, "a lamp", ROUTE)
    assert page.shows()[-1] == ("a lamp", False, "history")
    assert answers.pick(1, ("text", "never asked", ROUTE)) is False
    assert page.has("failed", "no longer in the history")


def test_each_export_is_its_own_job(protocol):
    session, answers, page = protocol
    answers.ask(1, "a chair", ROUTE)
    wait_for(lambda: ("a chair", False, "route") in page.shows(), "the answer")
    session.export_gate.clear()  # the first export blocks the worker
    assert answers.export(1, "selection", "#ff0000")
    wait_for(lambda: answers.worker.busy(), "the export running")
    assert answers.export(1, "subset", "#ff0000")  # never cancels the first
    assert answers.export(1, "invert", "#ff0000")
    session.export_gate.set()
    wait_for(lambda: len(session.exported) == 3, "three exports")
    assert [w for _, w in session.exported] == ["selection", "subset", "invert"]
    # a page has at most max_exports under way
    session.export_gate.clear()
    for _ in range(answers.max_exports):
        assert answers.export(1, "selection", "#ff0000")
    assert not answers.export(1, "selection", "#ff0000")
    assert page.has("failed", "exports are under way")
    session.export_gate.set()


def test_a_preview_cannot_be_exported(protocol):
    session, answers, page = protocol
    release = threading.Event()

    def partial_only(control: Control) -> Answer:
        control.partial(answer_of("p", final=False))
        release.wait()
        return answer_of("p")

    session.plan["p"] = partial_only
    answers.ask(1, "p", ROUTE)
    wait_for(lambda: ("p", True, "route") in page.shows(), "the preview")
    assert not answers.export(1, "selection", "#ff0000")
    assert page.has("failed", "wait for its final answer")
    release.set()


def test_a_wait_for_the_index_lock_frees_the_cores_shows_and_can_be_cancelled(protocol, tmp_path):
    session, answers, page = protocol
    session.lock_path = tmp_path / "index.h5"
    tries = []

    def needs_index(control: Control) -> Answer:
        tries.append(1)
        with output_lock(session.lock_path, "--res-index"):  # another process holds it
            return answer_of("indexed")

    session.plan["indexed"] = needs_index
    with output_lock(session.lock_path, "--res-index"):
        answers.ask(1, "indexed", ROUTE)
        wait_for(lambda: page.has("note", "waiting for it"), "the wait shown in the page")
        # the cores are free meanwhile: an urgent render gets the gate at once
        got = threading.Event()

        def render() -> None:
            with answers.worker.gate.urgent():
                got.set()

        threading.Thread(target=render, daemon=True).start()
        assert got.wait(30)
        # a new request cancels the wait, and is answered while the lock is still held
        answers.ask(1, "other", ROUTE)
        wait_for(lambda: ("other", False, "route") in page.shows(), "the other answer")
        wait_for(lambda: not answers.worker.busy(), "the wait ended")
        assert len(tries) == 1  # tried once, then waited without trying again
        answers.ask(1, "indexed", ROUTE)
        wait_for(lambda: len(tries) == 2 and answers.worker.busy(), "waiting again")
    # the other process let go: the answer comes
    wait_for(lambda: ("indexed", False, "route") in page.shows(), "the answer after the wait")
    assert ("indexed", False, "route") not in page.shows()[:-1]


def test_a_bug_is_one_line_in_the_page_and_a_traceback_in_the_log(protocol):
    session, answers, page = protocol
    lines = []
    answers.log = lines.append

    def broken(control: Control) -> Answer:
        raise ZeroDivisionError("oops")

    def refused(control: Control) -> Answer:
        raise GoiError("no embedding for 'bad'")

    session.plan["x"] = broken
    session.plan["bad"] = refused
    answers.ask(1, "x", ROUTE)
    wait_for(lambda: page.has("failed"), "the failure shown")
    assert page.has("failed", "a bug") and not page.has("failed", "oops")
    assert any("Traceback" in line and "ZeroDivisionError" in line for line in lines)
    answers.ask(1, "bad", ROUTE)
    wait_for(lambda: page.has("failed", "no embedding"), "the refusal shown")
    assert page.has("idle")


def test_bad_prompts_are_refused_in_the_page(protocol):
    _, answers, page = protocol
    assert answers.ask(1, "   ", ROUTE) is None
    assert answers.ask(1, "a\x00b", ROUTE) is None
    assert answers.ask(1, "ok", "no such route") is None
    assert [e[0] for e in page.events] == ["failed"] * 3
    assert answers.shown(1) is None


def test_the_history_is_bounded_in_bytes():
    from stages.view.answers import History

    one = answer_of("a").nbytes()
    h = History(max_bytes=5 * one)
    for i in range(50):
        h.add(answer_of(f"prompt {i}"))
    assert h.nbytes() <= 5 * one and len(h.answers()) == 5
    assert [a.prompt.text for a in h.answers()] == [f"prompt {i}" for i in range(45, 50)]
    # the newest is always kept, even alone over the bound
    big = History(max_bytes=1)
    big.add(answer_of("x"))
    assert len(big.answers()) == 1


# -- the real session on a RES index that another process replaces --------------------------


@pytest.mark.slow
def test_an_index_replaced_underneath_is_read_again(photographed, res_bundles, tmp_path):  # noqa: F811
    from goi_cli.main import main
    from stages.query.pipeline import PromptSources
    from stages.scene.scene import load_scene
    from stages.view.session import ViewRun, ViewSession

    s, _ = photographed
    bundle = res_bundles["grounded"]
    idx = tmp_path / "index.h5"
    session = ViewSession(
        load_scene(s["scene"]),
        None,
        PromptSources(bundle=bundle, res_index=idx),
        ViewRun(out=tmp_path / "view"),
    )
    first = session.answer("the red box", ROUTE)
    # another process builds the index anew over it: another file, with half the views
    argv = ["index-res", "--scene", str(s["scene"]), "--bundle", str(bundle), "--out",
            str(idx), "--force", "--part", "1/2"]  # fmt: skip
    assert main(argv) == 0
    again = session.answer("the red box", ROUTE)
    np.testing.assert_array_equal(first.selected, again.selected)
    assert session.answer("the green lamp", ROUTE).final


def test_a_page_asking_too_fast_is_refused_there(protocol):
    _, answers, page = protocol
    answers.prompts_per_s = 0.5  # 5 in any 10 s
    for i in range(5):
        assert answers.ask(1, f"prompt {i}", ROUTE) is not None
    assert answers.ask(1, "one more", ROUTE) is None
    assert page.has("failed", "5 prompts in 10 s from this page")
    answers.open(2, Recorder())  # another page has its own count
    assert answers.ask(2, "from another page", ROUTE) is not None


def test_a_flood_of_prompts_from_four_pages_stays_within_the_memory_bound(protocol):
    import tracemalloc

    session, answers, _ = protocol
    answers.history.max_bytes = 16 << 20
    answers.prompts_per_s = 1e6
    pages = [1, 2, 3, 4]
    for p in pages[1:]:
        answers.open(p, Recorder())
    big = 2_000_000  # each answer's selection: 2 MB

    def answer(text: str) -> Answer:
        return Answer(Prompt(text), ROUTE, np.ones(big, bool), "scripted")

    session.answer = lambda text, route, control: answer(text)  # type: ignore[method-assign]
    answers.undo_bytes = 4 << 20  # each page's steps
    tracemalloc.start()
    try:
        for i in range(400):  # 800 MB of answers, were they all kept
            answers.ask(pages[i % 4], f"prompt {i}", ROUTE)
            if i % 50 == 49:
                wait_for(lambda: not answers.worker.busy(), "the worker idle")
        wait_for(lambda: not answers.worker.busy(), "the worker idle")
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert answers.history.nbytes() <= 16 << 20
    # the history, each page's steps (the same answers, mostly) and answer on display
    assert held < (16 << 20) + 4 * (4 << 20) + 4 * big + (4 << 20), held


# -- clicks, steps, named answers ---------------------------------------------------------------


def _final(page: Recorder, text: str) -> None:
    wait_for(lambda: (text, False, "route") in page.shows(), f"the answer {text!r}")


def test_every_final_answer_is_a_step_and_undo_redo_walk_them(protocol):
    _, answers, page = protocol
    answers.ask(1, "a chair", ROUTE)
    _final(page, "a chair")
    answers.ask(1, "a lamp", ROUTE)
    _final(page, "a lamp")
    items, at = page.last_steps()
    assert at == 2 and items[0] == "nothing selected" and "a lamp" in items[2]
    assert answers.undo(1)
    assert page.shows()[-1] == ("a chair", False, "step") and page.last_steps()[1] == 1
    assert answers.undo(1)
    assert page.events[-3][0] == "clear" and answers.shown(1) is None
    assert not answers.undo(1) and page.has("failed", "nothing to undo")
    assert answers.redo(1) and page.shows()[-1] == ("a chair", False, "step")
    # a new answer after an undo drops the steps after it
    answers.ask(1, "a sofa", ROUTE)
    _final(page, "a sofa")
    items, at = page.last_steps()
    assert at == 2 and len(items) == 3 and "a sofa" in items[2]
    assert not answers.redo(1) and page.has("failed", "nothing to redo")
    # a history pick is a step too
    assert answers.pick(1, ("text", "a lamp", ROUTE))
    assert page.last_steps()[1] == 3


def test_an_undo_drops_the_answer_under_way(protocol):
    session, answers, page = protocol
    answers.ask(1, "a chair", ROUTE)
    _final(page, "a chair")
    started, release = threading.Event(), threading.Event()

    def slow(control: Control) -> Answer:
        started.set()
        release.wait()
        return answer_of("slow")  # (a job that does not look at its cancellation)

    session.plan["slow"] = slow
    answers.ask(1, "slow", ROUTE)
    assert started.wait(30)
    assert answers.undo(1)  # back to "a chair", while "slow" still runs
    release.set()
    wait_for(lambda: not answers.worker.busy(), "the worker idle")
    assert [s for s in page.shows() if s[0] == "slow"] == []
    assert answers.shown(1).answer.prompt.text == "a chair" and page.last_steps()[1] == 1
    # a preview on display: undo goes back to the step shown before it was asked
    session.plan["refining"] = lambda c: (
        c.partial(answer_of("refining", final=False)),
        release.clear(),
        release.wait(),
        answer_of("x"),
    )[-1]
    answers.ask(1, "refining", ROUTE)
    wait_for(lambda: ("refining", True, "route") in page.shows(), "the preview")
    assert answers.undo(1) and answers.shown(1).answer.prompt.text == "a chair"
    release.set()
    assert answers.undo(1) and answers.shown(1) is None  # and then to nothing


def test_a_click_refines_the_answer_shown_and_is_a_step(protocol):
    from stages.query.pointing import BoxPrompt, Click

    session, answers, page = protocol
    answers.ask(1, "a chair", ROUTE)
    _final(page, "a chair")
    chair = answers.shown(1).answer
    cam = {"page1-view1": None}
    assert answers.point(1, [Click("page1-view1", 500, 3, True)], [], cam, "part") is not None
    wait_for(lambda: page.last_steps()[1] == 2, "the click's step")
    (clicks, boxes, base, granularity) = session.pointed[-1]
    assert base is chair and granularity == "part"
    shown = answers.shown(1).answer
    assert shown.kind == "click" and shown.prompt.text == "a chair + click at 500,3"
    np.testing.assert_array_equal(shown.selected[chair.selected], True)
    assert shown.selected[500:510].all()
    # a minus click on the click's answer takes its band out again
    answers.point(1, [Click("page1-view1", 500, 3, False)], [], cam, "object")
    wait_for(lambda: page.last_steps()[1] == 3, "the minus click's step")
    np.testing.assert_array_equal(answers.shown(1).answer.selected, chair.selected)
    assert answers.shown(1).answer.prompt.text.endswith("- click at 500,3")
    # a box is a request of its own kind; a SAM that takes boxes only refuses clicks
    session.boxes_only = True
    assert answers.point(1, [Click("v", 1, 1)], [], {}, "object") is None
    assert page.has("failed", "takes boxes only")
    assert answers.point(1, [], [BoxPrompt("v", (1, 2, 30, 40))], {}, "object") is not None
    wait_for(lambda: answers.shown(1).answer.kind == "box", "the box's answer")


def test_a_click_waits_for_no_preview(protocol):
    from stages.query.pointing import Click

    session, answers, page = protocol
    release = threading.Event()

    def refining(control: Control) -> Answer:
        control.partial(answer_of("p", final=False))
        release.wait()
        return answer_of("p")

    session.plan["p"] = refining
    answers.ask(1, "p", ROUTE)
    wait_for(lambda: ("p", True, "route") in page.shows(), "the preview")
    assert answers.point(1, [Click("v", 1, 1)], [], {}, "object") is None
    assert page.has("failed", "still refining")
    release.set()
    _final(page, "p")
    assert answers.point(1, [Click("v", 1, 1)], [], {}, "object") is not None


def test_named_answers_combine_into_a_step(protocol):
    _, answers, page = protocol
    a, b = answer_of("a chair").selected, answer_of("a lamp").selected
    answers.ask(1, "a chair", ROUTE)
    _final(page, "a chair")
    assert answers.keep(1, " chair ")  # names are trimmed
    answers.ask(1, "a lamp", ROUTE)
    _final(page, "a lamp")
    assert answers.keep(1, "lamp")
    assert [n for n, _ in answers.named()] == ["chair", "lamp"]
    expected = {"union": a | b, "intersection": a & b, "difference": a & ~b, "invert": ~a}
    for i, (op, sel) in enumerate(expected.items()):
        assert answers.combine(1, op, "chair", "lamp") is not None
        wait_for(lambda i=i: page.last_steps()[1] == 3 + i, f"the {op} step")
        shown = answers.shown(1).answer
        assert shown.kind == "combine"
        np.testing.assert_array_equal(shown.selected, sel)
    assert answers.shown(1).answer.prompt.text == "not (chair)"
    # the answer shown is an operand too; undo walks back over the combinations
    assert answers.combine(1, "union", SHOWN, "lamp") is not None
    wait_for(lambda: page.last_steps()[1] == 7, "the last step")
    np.testing.assert_array_equal(answers.shown(1).answer.selected, ~a | b)
    assert answers.undo(1)
    np.testing.assert_array_equal(answers.shown(1).answer.selected, ~a)
    # refusals: an unknown name, an unknown operation, a bad name; forgetting a name
    assert answers.combine(1, "union", "chair", "nope") is None
    assert answers.combine(1, "xor", "chair", "lamp") is None
    assert not answers.keep(1, "") and not answers.keep(1, "x" * 61)
    assert not answers.keep(1, SHOWN) and not answers.keep(1, 3)
    assert page.has("failed", "not one of the named answers")
    assert page.has("failed", "the operation is one of")
    assert answers.forget(1, "chair") and [n for n, _ in answers.named()] == ["lamp"]
    assert not answers.forget(1, "chair")


def test_named_answers_are_bounded_and_never_evicted(protocol):
    _, answers, page = protocol
    answers.named_bytes = 3 * answer_of("x").nbytes()
    for i in range(3):
        answers.ask(1, f"p{i}", ROUTE)
        _final(page, f"p{i}")
        assert answers.keep(1, f"n{i}")
    answers.ask(1, "p3", ROUTE)
    _final(page, "p3")
    assert not answers.keep(1, "n3") and page.has("failed", "forget one first")
    assert answers.keep(1, "n2")  # a name replaced: within the bound
    assert [n for n, _ in answers.named()] == ["n0", "n1", "n2"]


def test_a_pages_steps_are_bounded_in_bytes(protocol):
    _, answers, page = protocol
    answers.undo_bytes = 3 * answer_of("x").nbytes()
    for i in range(6):
        answers.ask(1, f"p{i}", ROUTE)
        _final(page, f"p{i}")
    items, at = page.last_steps()
    assert len(items) == 3 and at == 2 and "p5" in items[2] and "p3" in items[0]
    assert answers.undo(1) and answers.undo(1) and not answers.undo(1)
