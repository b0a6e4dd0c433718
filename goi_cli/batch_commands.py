"""`goi batch CONFIG`: parse, check the configuration, run the workflow, print its table."""

from __future__ import annotations

from pathlib import Path

import click

from goi_cli.options import build, dataclass_options
from goi_cli.report import TERMINAL
from stages.batch.run import BatchRun
from stages.core.errors import GoiError


@click.command(
    "batch",
    context_settings={"ignore_unknown_options": False, "allow_interspersed_args": True},
    short_help="Run many scenes and prompts as one Snakemake workflow.",
)
@click.argument("config", type=click.Path(path_type=Path))
@click.argument("snakemake_args", nargs=-1, type=click.UNPROCESSED)
@dataclass_options(BatchRun)
def batch_cmd(config: Path, snakemake_args: tuple[str, ...], **kw) -> None:
    """Run many scenes and prompts as one Snakemake workflow, locally or on a cluster.

    CONFIG (YAML or JSON, schema goi.batch; docs/scaling.md) lists the scenes (a directory or
    ply/cameras/images, a features source, a RES source or bundle, an optional RES index) and
    their prompts. Each goi stage is one job: extract, init-codebook and fit-field per scene,
    index-res when asked, then one query per prompt; a scene without features goes the
    field-free lifted route. A rerun runs only what is out of date. It ends with one table:
    per scene the stages run, their time and the answers written.

    Snakemake's own options go after `--`, e.g. `goi batch c.yaml --executor slurm --jobs 100
    -- --default-resources slurm_account=X` or `--executor cluster-generic --
    --cluster-generic-submit-cmd 'sbatch ...'`; not those goi batch sets itself (--config,
    --configfile, --snakefile, --directory, the profiles, the lock). Every stage's inputs are
    checked before the first job; no Snakemake profile is loaded but the one --profile names.
    Needs `pip install 'goi[batch]'`.
    """
    from stages.batch.config import load_batch
    from stages.batch.run import (
        check_snakemake_args,
        last_line,
        profile_file,
        run_batch,
        snakemake_available,
    )

    snakemake_available()  # before the configuration: nothing can run without it
    run = build(BatchRun, kw)
    # Snakemake's arguments and the profile are refused before the configuration's scenes,
    # bundles and indexes are loaded and checked (seconds); run_batch checks them again for
    # its other callers (milliseconds)
    check_snakemake_args(list(snakemake_args))
    if run.profile is not None:
        profile_file(run.profile)
    batch = load_batch(config, run.out)
    _check_options(batch)
    result = run_batch(batch, run, list(snakemake_args), TERMINAL)
    if result.dry_run:
        if result.returncode != 0:
            raise click.exceptions.Exit(result.returncode)
        return
    click.echo("\n".join(result.table()))
    failed = [log for s in result.scenes for log in s.failed]
    if result.returncode != 0:
        where = f"; {failed[0]}: {last_line(failed[0])}" if failed else ""
        click.echo(
            f"goi: error: batch: Snakemake stopped with exit status {result.returncode}{where}",
            err=True,
        )
        raise click.exceptions.Exit(1)


def _check_options(batch: object) -> None:
    """Every option a scene adds to a stage is one that goi command has, with a value of its
    type and range: parsed by the command's own click option (checked here, where the commands
    are known, before any job runs)."""
    from stages.batch.config import Batch

    assert isinstance(batch, Batch)
    goi = click.get_current_context().find_root().command
    assert isinstance(goi, click.Group)
    for s in batch.scenes:
        for (stage, name), (line, value) in s.option_values.items():
            command = goi.commands[stage]
            where = f"{batch.config}: line {line}: 'options.{stage}.{name}'"
            param = next((p for p in command.params if f"--{name}" in p.opts), None)
            if not isinstance(param, click.Option):
                raise GoiError(
                    f"{where}: goi {stage} has no option --{name} (see goi {stage} --help)"
                )
            if param.is_flag != isinstance(value, bool):
                want = "true or false (a flag)" if param.is_flag else "a value, not true/false"
                raise GoiError(f"{where}: --{name} takes {want}")
            if param.is_flag:
                continue
            try:
                param.type_cast_value(click.Context(command), str(value))
            except click.BadParameter as e:
                raise GoiError(f"{where}: {e.message}") from None


def register(group: click.Group) -> None:
    group.add_command(batch_cmd)
