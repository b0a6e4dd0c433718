import contextlib

from goi_cli.report import TERMINAL
from stages.core.report import SILENT, Lines


def test_silent_yields_every_item_and_says_nothing(capsys):
    assert list(SILENT.progress(range(7), "x", length=7)) == list(range(7))
    SILENT.log("not shown")
    assert capsys.readouterr() == ("", "")


def test_a_long_loop_without_a_bar_says_how_far_it_got_every_few_percent():
    lines: list[str] = []
    report = Lines(write=lines.append, quiet_s=0.0)
    got = list(report.progress(range(200), "fit-field", length=200, show=lambda i: f"at {i}"))
    assert got == list(range(200))
    assert len(lines) == 20  # every 5 %: items 10, 20, ..., 200
    assert lines[0].startswith("fit-field: 10/200 (5%), ") and lines[0].endswith(", at 9")
    assert lines[-1].startswith("fit-field: 200/200 (100%), ")


def test_a_quick_loop_stays_quiet_and_news_is_written():
    lines: list[str] = []
    report = Lines(write=lines.append)  # lines only once a loop has run 5 s
    assert list(report.progress(range(50), "quick", length=50)) == list(range(50))
    report.log("news")
    assert lines == ["news"]


def test_a_bar_is_used_where_it_can_be_drawn():
    used = []

    @contextlib.contextmanager
    def bar(items, label, length, show):
        used.append((label, length))
        yield items

    lines: list[str] = []
    report = Lines(write=lines.append, bar=bar, quiet_s=0.0)
    assert list(report.progress(range(40), "b", length=40)) == list(range(40))
    assert used == [("b", 40)] and lines == []


def test_the_cli_report_writes_lines_on_stderr_when_it_is_not_a_terminal(capsys, monkeypatch):
    monkeypatch.setattr(TERMINAL, "quiet_s", 0.0)
    assert list(TERMINAL.progress(range(20), "fit-field", length=20)) == list(range(20))
    TERMINAL.log("done")
    out, err = capsys.readouterr()
    assert out == ""  # stdout holds only results
    assert err.splitlines()[0].startswith("goi: fit-field: 1/20 (5%), ")
    assert len(err.splitlines()) == 21 and err.splitlines()[-1] == "goi: done"
