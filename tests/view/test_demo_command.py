"""A new user's first command: the `goi view` line `goi demo` prints runs as printed, installs
what it needs on its first use, and is the README's."""

import re
import shlex
from pathlib import Path
from types import SimpleNamespace

import pytest

from goi_cli.main import main
from stages.evaluation.demo import view_command

REPO = Path(__file__).resolve().parents[2]


def test_the_demo_prints_the_readmes_view_command_and_it_runs(monkeypatch, tmp_path):
    pytest.importorskip("viser")
    monkeypatch.chdir(REPO)
    printed = view_command(SimpleNamespace(field=REPO / "goi-demo" / "field.h5"))  # type: ignore[arg-type]
    readme = (REPO / "README.md").read_text()
    block = readme[readme.index("### Prompts in the browser") :]
    shown = re.search(r"```bash\n(.*?)\n```", block, re.S)
    assert shown is not None
    assert shlex.split(shown.group(1).replace("\\\n", " ")) == shlex.split(printed)
    # it goes through the script that installs the view extra on its first use
    argv = shlex.split(printed)
    assert argv[:3] == ["bash", "scripts/goi.sh", "view"]
    script = (REPO / "scripts" / "goi.sh").read_text()
    assert 'view) GOI_EXTRAS="[view]"' in script
    # and `goi view` takes every option it gives (the demo's field aside, which only the demo
    # makes: the field-free route answers without it)
    args = argv[3:]
    i = args.index("--field")
    args = [*args[:i], *args[i + 2 :]]
    args[args.index("--out") + 1] = str(tmp_path / "view")
    assert main(["view", *args, "--port", "0", "--for-seconds", "0.1"]) == 0
