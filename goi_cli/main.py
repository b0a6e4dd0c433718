"""The `goi` program: one subcommand per stage, clean errors, exit codes 0 / 1 / 2."""

from __future__ import annotations

import signal
import sys
import traceback
import warnings
from collections.abc import Sequence

import click

from goi_cli import batch_commands, commands, eval_commands, query_commands, view_commands
from stages import __version__
from stages.core.artifacts import set_command
from stages.core.errors import GoiError, debugging, set_debug
from stages.core.files import guarded_inputs
from stages.core.interrupts import stoppable


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="goi")
@click.option(
    "--debug",
    is_flag=True,
    help="Show the full traceback when something fails "
    "(also GOI_DEBUG=1). Accepted anywhere on the command line.",
)
def cli(debug: bool) -> None:
    """Find the 3D Gaussians of interest in a 3D Gaussian Splatting scene from a text prompt.

    Each stage reads and writes explicit artifact files (HDF5 or PLY) whose schema and
    provenance are recorded inside; `goi inspect FILE` shows what a file holds.
    """


commands.register(cli)
query_commands.register(cli)
eval_commands.register(cli)
batch_commands.register(cli)
view_commands.register(cli)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    print(f"goi: warning: {message}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    set_debug("--debug" in args)
    debug = debugging()
    args = [a for a in args if a != "--debug"]
    set_command(["goi", *args])
    old_show = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        # no output of this command may replace one of its inputs; a Ctrl-C always stops it
        with guarded_inputs(), stoppable():
            rc = cli.main(args=args, prog_name="goi", standalone_mode=False)
        code = rc if isinstance(rc, int) else 0
    except click.exceptions.Abort:
        print("goi: interrupted", file=sys.stderr)
        code = 130
    except KeyboardInterrupt:
        print("goi: interrupted", file=sys.stderr)
        code = 130
    except click.exceptions.NoArgsIsHelpError as e:
        e.show()  # `goi` alone, or a group without a command: the help
        code = 2
    except click.ClickException as e:
        # One line, like goi's own errors; click names the option or argument.
        hint = ""
        if isinstance(e, click.UsageError) and e.ctx is not None:
            hint = f" (see {e.ctx.command_path} --help)"
        print(f"goi: error: {' '.join(e.format_message().split())}{hint}", file=sys.stderr)
        code = e.exit_code if e.exit_code else 2
    except GoiError as e:
        if debug:
            traceback.print_exc()
        print(f"goi: error: {e}", file=sys.stderr)
        code = 2
    except Exception as e:  # a bug in goi, not the user's input
        if debug:
            traceback.print_exc()
        # some libraries put whole tensors in their messages: keep the first line
        first = (str(e).splitlines() or [""])[0][:300]
        print(
            f"goi: internal error: {type(e).__name__}: {first} (run with --debug for the "
            "traceback)",
            file=sys.stderr,
        )
        code = 1
    finally:
        warnings.showwarning = old_show
    return code


def entry() -> None:
    code = main()
    # The command is over and its artifacts are in place: a Ctrl-C that lands during the
    # interpreter's shutdown must not turn a finished run into one killed by SIGINT.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)
