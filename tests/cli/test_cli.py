import subprocess
import sys

import pytest

from goi_cli.main import cli, main
from tests.helpers import DEV_ROOM, random_vertex, write_ply


def test_help_lists_the_built_stages(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "inspect" in out
    listed = out[out.index("Commands:") :].splitlines()[1:]
    # every command's summary is whole, on one line of an 80-column terminal
    assert len(listed) == len(cli.commands) and all(line.rstrip().endswith(".") for line in listed)
    assert not any("..." in line or "\u2026" in line for line in listed)
    assert any(
        line.split() == ["extract-features", "An", "alias", "of", "extract."] for line in listed
    )
    assert main(["extract-features", "--help"]) == 0
    assert "The same command as `goi extract` (an alias)." in capsys.readouterr().out


def test_inspect_a_good_ply(tmp_path, capsys):
    p = write_ply(tmp_path / "a.ply", random_vertex(30, degree=2))
    assert main(["inspect", str(p)]) == 0
    out = capsys.readouterr().out
    assert "gaussians     30" in out and "sh degree     2" in out and "0 errors" in out


def test_user_error_is_one_line_exit_2_without_traceback(tmp_path, capsys):
    p = tmp_path / "bad.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    assert main(["inspect", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert str(p) in err and "missing" in err


def test_debug_shows_the_traceback(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "nope.h5"), "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "nope.h5: no such file" in err


def test_bad_option_exits_2(capsys):
    assert main(["inspect"]) == 2
    assert main(["--no-such-option"]) == 2


def test_console_script_runs():
    r = subprocess.run(
        [sys.executable, "-m", "goi_cli", "--version"], capture_output=True, text=True
    )
    assert r.returncode == 0 and "goi, version" in r.stdout


@pytest.mark.skipif(not DEV_ROOM.is_dir(), reason="shared/dev-room is not beside the checkout")
def test_inspect_dev_room_ply_shows_no_errors(capsys):
    assert main(["inspect", str(DEV_ROOM / "point_cloud.ply")]) == 0
    out = capsys.readouterr().out
    assert "gaussians     121022" in out and "0 errors" in out


def test_the_command_line_is_built_without_torch():
    """torch takes ~1 s to import; only the commands that fit a field or run it need it, so
    building the command line (every `goi ...` call) must not import it."""
    code = (
        "import sys, goi_cli.main\n"
        "print(sorted(m for m in ('torch', 'transformers') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
