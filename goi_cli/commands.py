"""Subcommands. Each one parses its options, calls one stage function and reports."""

from __future__ import annotations

import click

from stages.errors import GoiError


@click.command("inspect")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
def inspect_cmd(files: tuple[str, ...]) -> None:
    """Show what a PLY or HDF5 artifact holds and validate it against its schema.

    Exits 2 when any file has problems.
    """
    from stages.inspect import inspect_file

    total = 0
    for path in files:
        lines, problems = inspect_file(path)
        click.echo("\n".join(lines))
        for p in problems:
            click.echo(f"  problem       {p}")
        click.echo(f"  {len(problems)} errors")
        total += len(problems)
    if total:
        raise GoiError(f"{total} problem(s) found")


def register(group: click.Group) -> None:
    group.add_command(inspect_cmd)
