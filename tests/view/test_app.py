"""goi view's server with pages on the wire (stages.testing.view_client, no browser): two tabs
asking at once each get their own prompt's answer; a page shows what a user typed as text,
never as markup; the scene reaches a page in chunks."""

import html
import json
import time

import numpy as np
import pytest

from stages.query.pipeline import PromptSources
from stages.scene.scene import load_scene
from stages.view.session import ViewRun, ViewSession
from tests.helpers import write_true_res

pytest.importorskip("viser")


@pytest.fixture(scope="module")
def session(fitted, tmp_path_factory):
    s, run = fitted
    root = tmp_path_factory.mktemp("view_app")
    write_true_res(s, root, range(len(s["objects"])))
    prompts = [{"id": f"o{k}", "text": f"object {k}"} for k in range(len(s["objects"]))]
    (root / "prompts.json").write_text(json.dumps(prompts))
    return ViewSession(
        load_scene(s["scene"]),
        run / "field.h5",
        PromptSources(text_embeddings=root / "text.json", res_masks=root / "res"),
        ViewRun(out=root / "out", prompts=root / "prompts.json", port=0),
    )


@pytest.fixture
def served(session):
    from stages.testing.view_client import Client
    from stages.view.app import ViewerApp

    app = ViewerApp(session)
    url = app.start()
    clients = [Client(url), Client(url)]
    for _ in range(400):
        if len(app.pages) == 2:
            break
        time.sleep(0.05)
    assert len(app.pages) == 2
    try:
        yield app, clients
    finally:
        for c in clients:
            c.close()
        app.stop()


def _final(page, text):
    from tests.view.served import wait_for

    def done():
        s = page.shown
        return s is not None and not s.preview and s.answer.prompt.text == text

    wait_for(done, f"the final answer to {text!r}", timeout=600)
    return page.shown.answer


@pytest.mark.slow
def test_two_tabs_asking_at_once_get_their_own_answers(served, session):
    app, clients = served
    a, b = app.pages.values()
    a.route = b.route = "lifted"
    a.ask("object 1")
    b.ask("object 2")
    ans_a, ans_b = _final(a, "object 1"), _final(b, "object 2")
    history = app.answers.history
    np.testing.assert_array_equal(
        ans_a.selected, history.get(("text", "object 1", "lifted")).selected
    )
    np.testing.assert_array_equal(
        ans_b.selected, history.get(("text", "object 2", "lifted")).selected
    )
    assert not np.array_equal(ans_a.selected, ans_b.selected)
    # both pages list both answers in their history
    from tests.view.served import wait_for

    def listed(page) -> set:
        return {k[1] for k in page.history_keys.values()}

    wait_for(lambda: all({"object 1", "object 2"} <= listed(p) for p in (a, b)), "the history")


@pytest.mark.slow
def test_a_new_prompt_supersedes_the_pages_unfinished_one(served, session):
    app, _ = served
    a, _b = app.pages.values()
    a.route = "lifted"
    a.ask("object 3")
    a.ask("object 4")  # at once: the first is cancelled before or during its lift
    _final(a, "object 4")
    from tests.view.served import wait_for

    wait_for(lambda: not app.worker.busy(), "the worker idle")
    assert a.shown.answer.prompt.text == "object 4" and not a.shown.preview


@pytest.mark.slow
def test_what_a_user_typed_is_shown_as_text(served):
    app, _ = served
    page = next(iter(app.pages.values()))
    typed = "<img src=x onerror=alert(1)> & friends"
    page.route = "threshold"  # the prompt has no embedding: the error names it
    page.ask(typed)
    from tests.view.served import wait_for

    wait_for(lambda: "#b00020" in page.status.content, "the error shown")
    assert html.escape(typed) in page.status.content and "<img" not in page.status.content


@pytest.mark.slow
def test_the_scene_reaches_a_page_in_chunks(served):
    app, clients = served
    _, nbytes = clients[0].settled(quiet=3.0)
    splat_bytes = app.splats.count * 32
    assert nbytes >= 0.9 * splat_bytes, (nbytes, splat_bytes)
    assert app.splats.count == app.session.scene.gaussians.count
