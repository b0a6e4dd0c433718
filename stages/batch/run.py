"""`goi batch`: the shipped Snakefile run on a checked configuration, and its summary.

Snakemake runs as `python -m snakemake` in a child process of the same interpreter (so its
jobs, which run `python -m goi`, see the same goi), in the batch's output directory: its
metadata (`.snakemake/`) lives there, so a rerun of the same batch runs only what is out of
date; goi's own lock there refuses a second `goi batch` of one output directory. The summary
is made from the files the jobs wrote (each rule's benchmark and log), not from Snakemake's
messages.

goi batch owns Snakemake's command line. Snakemake on its own loads a workflow profile from
the working directory (`profiles/default/`) and a profile named by $SNAKEMAKE_PROFILE; a
profile can set any option, `config: [python=...]` included, which would make any program the
interpreter of every job. So no profile is loaded unless `--profile` names one, the
options goi sets itself are refused after `--` and in that profile (`OWNED`), and OUT is
goi batch's own: new, empty, or made by goi batch (`OUT/.goi-batch/`), unless `--force`.
"""

from __future__ import annotations

import contextlib
import csv
import importlib.util
import os
import subprocess
import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Annotated

from stages.batch.config import Batch, PromptJob, SceneJob
from stages.core.artifacts import write_json
from stages.core.errors import GoiError
from stages.core.files import check_out_dir, make_dir, output_lock
from stages.core.params import Range
from stages.core.report import SILENT, Report

#: The extra that brings Snakemake (pyproject.toml).
INSTALL = "pip install 'goi[batch]'"


@dataclass
class BatchRun:
    out: Path | None = None
    """Output directory of the batch (default: the configuration's 'out', else goi-batch
    beside it): <scene>/ per scene, Snakemake's state in .snakemake/."""
    jobs: Annotated[int, Range(ge=1, le=10_000)] = 1
    """Jobs at once: local processes, or jobs submitted to the cluster with --executor. goi's
    stages are multi-threaded already: locally, a few jobs overlap one's reading and writing
    with another's work."""
    executor: str = "local"
    """Snakemake executor: local, or a plugin such as slurm or cluster-generic (installed with
    pip, e.g. snakemake-executor-plugin-slurm); its settings go after --, as Snakemake's."""
    dry_run: bool = False
    """Show the jobs that would run, and why, without running them."""
    keep_going: bool = False
    """Go on with the jobs that do not depend on a failed one."""
    profile: Path | None = None
    """A Snakemake profile (its directory, holding config.yaml or profile.yaml, or that file),
    e.g. a cluster's settings. No other profile is ever loaded: not $SNAKEMAKE_PROFILE, not a
    profiles/ directory where goi batch is started. The options goi batch sets itself may not
    be in it."""
    force: bool = False
    """Run in an --out that holds files goi batch did not make (Snakemake replaces the
    outputs it reruns, e.g. a features.h5 of yours in OUT/<scene>/)."""


@dataclass
class SceneSummary:
    name: str
    stages: list[str] = field(default_factory=list)  # the jobs that ran, e.g. query-<prompt>
    seconds: float = 0.0  # their wall time, from their benchmark files
    new_answers: int = 0
    answers: int = 0  # present after the run
    prompts: int = 0
    failed: list[Path] = field(default_factory=list)  # logs of jobs that did not finish


@dataclass
class BatchResult:
    out: Path
    returncode: int
    dry_run: bool
    scenes: list[SceneSummary]

    def table(self) -> list[str]:
        """One line per scene: the stages run, their time, the answers written."""
        rows = [("scene", "stages run", "time", "answers")]
        for s in self.scenes:
            rows.append(
                (
                    s.name,
                    _stages_text(s.stages, [f.stem for f in s.failed]),
                    f"{s.seconds:.1f} s",
                    f"{s.new_answers} new, {s.answers}/{s.prompts}",
                )
            )
        widths = [max(len(r[i]) for r in rows) for i in range(4)]
        return [
            "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows
        ]


def snakefile() -> Path:
    return Path(str(resources.files("stages.batch").joinpath("workflow/Snakefile")))


def snakemake_available() -> None:
    if importlib.util.find_spec("snakemake") is None:
        raise GoiError(f"goi batch needs Snakemake: {INSTALL}")


#: Snakemake's options (their argparse dest) that goi batch sets itself, and why: refused
#: after `--` and in a --profile, under any spelling (`-C`, `--configf`, `-nd DIR`).
OWNED = {
    "snakefile": "it runs its own workflow",
    "directory": "the workflow runs in OUT: use goi batch --out",
    "configfile": "its plan, OUT/.goi-batch/plan.json, is the workflow's configuration",
    "config": "its plan, OUT/.goi-batch/plan.json, is the workflow's configuration",
    "profile": "name a profile with goi batch --profile",
    "workflow_profile": "name a profile with goi batch --profile",
    "nolock": "it locks OUT itself",
    "unlock": "it locks OUT itself",
}
#: The state directory of goi batch in OUT; it also marks OUT as goi batch's own.
STATE = ".goi-batch"


def check_snakemake_args(extra: list[str], where: str = "after --") -> None:
    """Refuse any of the OWNED options among Snakemake's own arguments, resolved the way
    Snakemake's parser resolves them (abbreviations, `--opt=value`, clustered short options)."""
    if not extra:
        return
    from snakemake.cli import get_argument_parser

    actions = get_argument_parser()._option_string_actions  # option string -> argparse action
    for tok in extra:
        if tok == "--":  # Snakemake's own: targets follow
            break
        if not tok.startswith("-") or tok == "-":
            continue
        if tok.startswith("--"):
            name = tok.split("=", 1)[0]
            hits = [name] if name in actions else [o for o in actions if o.startswith(name)]
        else:  # -nd DIR: each letter an option until one takes the rest as its value
            hits = []
            for ch in tok[1:]:
                action = actions.get(f"-{ch}")
                if action is None:
                    break
                hits.append(f"-{ch}")
                if action.nargs != 0:
                    break
        for option in hits:
            dest = actions[option].dest
            if dest in OWNED:
                canonical = next(o for o in actions[option].option_strings if o.startswith("--"))
                raise GoiError(
                    f"{tok[:80]} ({where}): goi batch sets Snakemake's {canonical} itself "
                    f"({OWNED[dest]}); leave it out"
                )


def profile_file(profile: Path) -> Path:
    """The YAML file of a profile named with --profile, found as Snakemake finds it in a
    directory, with none of the options goi batch sets (OWNED) among its keys."""
    from snakemake.cli import get_profile_dir

    from stages.batch.config import read_config

    p = Path(os.path.expanduser(profile))
    if not p.exists():
        raise GoiError(f"--profile: {p}: no such file or directory (a Snakemake profile)")
    found = get_profile_dir(str(p.resolve()))
    if found is None:
        raise GoiError(f"--profile: {p} holds no config.yaml or profile.yaml (a Snakemake profile)")
    yaml_file = found[1].resolve()
    root = read_config(yaml_file, "Snakemake profile")
    if not isinstance(root.value, dict):
        raise GoiError(f"--profile: {yaml_file}: not a mapping of Snakemake options")
    if "__use_yte__" in root.value:  # Snakemake would template it (Python) into other keys
        raise GoiError(
            f"--profile: {yaml_file}: a YTE template profile (__use_yte__) is refused: goi batch "
            "checks a profile's keys for the options it sets, and a template's keys are known "
            "only once Snakemake has run it; give a plain profile"
        )
    for key, node in root.value.items():  # a key is an option: `jobs` or `--jobs`
        option = key if key.startswith("--") else f"--{key}"
        check_snakemake_args([option], f"--profile {yaml_file}: line {node.line}")
    return yaml_file


def check_out(out: Path, force: bool) -> None:
    """OUT is goi batch's: new, empty, or made by goi batch (its state directory); else
    refused without --force, before anything is written: Snakemake deletes an output it is
    about to make again, whoever made it."""

    def ours() -> bool:
        state = out / STATE
        if state.is_symlink() or (state.exists() and not state.is_dir()):
            raise GoiError(f"--out: {state} is not goi batch's state directory (a link, a file?)")
        return state.is_dir()

    check_out_dir(out, force, "goi batch", ours, "Snakemake would replace those it writes")


def run_batch(
    batch: Batch, run: BatchRun, extra: list[str], report: Report = SILENT
) -> BatchResult:
    """Run the batch's workflow (`extra`: Snakemake's own arguments) and summarise it."""
    snakemake_available()
    check_snakemake_args(extra)
    profile = profile_file(run.profile) if run.profile is not None else None
    out = Path(run.out or batch.out)
    check_out(out, run.force)
    out = make_dir(out, "--out").resolve()
    state = make_dir(out / STATE, "--out")
    # One goi batch per output directory, dry runs included: the plan a running batch's jobs
    # read (a cluster job reads it again) is never rewritten under them, and the summary never
    # counts another run's jobs as this one's.
    with output_lock(state / "run", "--out"):
        return _run(batch, run, extra, out, state, profile, report)


def _run(
    batch: Batch,
    run: BatchRun,
    extra: list[str],
    out: Path,
    state: Path,
    profile: Path | None,
    report: Report,
) -> BatchResult:
    plan = state / "plan.json"
    write_json(plan, batch.plan(sys.executable), force=True)
    # The targets come first: Snakemake options such as --configfile or --set-resources take
    # any number of values, and would take targets given after them as theirs.
    cmd = [sys.executable, "-m", "snakemake", "all", *_missing_intermediates(out, batch)]
    cmd += [
        "--snakefile", str(snakefile()), "--directory", str(out), "--jobs", str(run.jobs),
        "--rerun-incomplete", "--configfile", str(plan),
        # no profile but the one named: not profiles/default/ in the working directory, not
        # $SNAKEMAKE_PROFILE (also dropped from the environment, for the jobs' Snakemake)
        "--workflow-profile", "none", "--profile", str(profile) if profile else "none",
    ]  # fmt: skip
    if run.executor != "local":
        cmd += ["--executor", run.executor]
    if run.dry_run:
        cmd.append("--dry-run")
    if run.keep_going:
        cmd.append("--keep-going")
    cmd += extra
    n_jobs = sum(len(s.prompts) + (3 if s.fitted else 0) + s.index_jobs for s in batch.scenes)
    n_prompts = sum(len(s.prompts) for s in batch.scenes)
    report.log(
        f"{_count(len(batch.scenes), 'scene')}, {_count(n_prompts, 'prompt')} "
        f"({_count(n_jobs, 'job')} when nothing is done yet) in {out}, executor {run.executor}"
    )
    before = _stamps(out, batch)
    env = {k: v for k, v in os.environ.items() if k != "SNAKEMAKE_PROFILE"}
    env["PYTHONUNBUFFERED"] = "1"
    # Snakemake prints its own progress; it goes to stderr (file descriptor 2) with goi's
    # news, and the table to stdout. A dry run has no table: what Snakemake prints on stdout
    # (e.g. `-- --dag`, the graph in DOT) stays there.
    stdout = None if run.dry_run else 2
    rc = subprocess.run(cmd, stdout=stdout, env=env, check=False).returncode
    return BatchResult(out, rc, run.dry_run, [_summary(out, s, before) for s in batch.scenes])


def _count(n: int, what: str) -> str:
    return f"{n} {what}{'s' * (n != 1)}"


def _missing_intermediates(out: Path, batch: Batch) -> list[str]:
    """The scenes' intermediate artifacts that are not there, as extra targets. Snakemake
    alone keeps answers whose intermediate input was deleted (it would only be needed to make
    them again); asked for it, it makes the artifact again, and then everything after it is out
    of date and reruns: a deleted artifact reruns what depends on it, and only that."""
    names = ["features.h5", "codebook.h5", "field.h5"]
    targets = []
    for s in batch.scenes:
        for name in [*names * s.fitted, *["res_index.h5"] * bool(s.index_bundle)]:
            if not (out / s.name / name).exists():
                targets.append(f"{s.name}/{name}")
    return targets


def _answer(out: Path, scene: SceneJob, p: PromptJob) -> Path:
    name = p.prompt.name
    return out / scene.name / "prompts" / name / name / "selection.h5"


def _stamps(out: Path, batch: Batch) -> dict[Path, tuple[int, int, int]]:
    """(mtime, inode, size) of every log, benchmark and answer of the batch. A file whose
    stamp changed was written by this run: no clock is compared, so a cluster node's clock
    that is off does not matter."""
    files: list[Path] = []
    for s in batch.scenes:
        files += (out / s.name / "logs").glob("*.log")
        files += (out / s.name / "logs").glob("*.tsv")
        files += [_answer(out, s, p) for p in s.prompts]
    stamps = {}
    for f in files:
        with contextlib.suppress(OSError):
            st = f.stat()
            stamps[f] = (st.st_mtime_ns, st.st_ino, st.st_size)
    return stamps


def _summary(out: Path, scene: SceneJob, before: dict[Path, tuple[int, int, int]]) -> SceneSummary:
    """What the jobs of one scene did in this run, from the files they wrote in it."""
    now = _stamps(out, Batch(Path(), out, [scene]))
    fresh = {f for f, st in now.items() if before.get(f) != st}
    s = SceneSummary(scene.name, prompts=len(scene.prompts))
    # A job that ran wrote its log; one that finished also wrote its benchmark (after it).
    for log in sorted((f for f in fresh if f.suffix == ".log"), key=lambda f: now[f][0]):
        bench = log.with_suffix(".tsv")
        if bench in fresh:
            s.stages.append(log.stem)
            s.seconds += _seconds(bench)
        else:
            s.failed.append(log)
    for p in scene.prompts:
        answer = _answer(out, scene, p)
        if answer in now:
            s.answers += 1
            s.new_answers += answer in fresh
    return s


def _seconds(bench: Path) -> float:
    """The wall time a Snakemake benchmark file records (column 's')."""
    with bench.open() as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    return sum(float(r.get("s") or 0) for r in rows)


def _stages_text(stages: list[str], failed: list[str]) -> str:
    """e.g. `extract, init-codebook, fit-field, query x2; failed: query x1`."""

    def names(jobs: list[str]) -> list[str]:
        queries = sum(st.startswith("query-") for st in jobs)
        named = [st for st in jobs if not st.startswith("query-")]
        return [*named, *([f"query x{queries}"] if queries else [])]

    text = ", ".join(names(stages)) or "-"
    return f"{text}; failed: {', '.join(names(failed))}" if failed else text


def last_line(log: Path) -> str:
    """The last line a failed job wrote (goi's one-line error), shortened."""
    try:
        lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][:300] if lines else ""
