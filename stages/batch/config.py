"""The configuration of `goi batch` (schema goi.batch): read, checked, resolved into a plan.

The file is YAML or JSON (JSON is YAML, so one reader serves both and every value keeps its
line). It is checked against schemas/goi.batch.json before anything runs: an unknown key, a
value of the wrong type, a key given twice, a missing scene, two scenes or two prompts
writing the same output are each one GoiError naming the file, the key and its line. The plan
is what the shipped Snakefile reads: plain paths and argument lists, nothing to import.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from schemas import current_version, definition
from stages.core.errors import GoiError
from stages.core.files import read_text
from stages.query.prompts import (
    Prompt,
    check_plain_name,
    check_prompt,
    load_text_embeddings,
    text_embedding,
)
from stages.query.res import ResFiles, checked_index
from stages.query.res_index import indexable_bundle
from stages.scene.scene import load_scene

if TYPE_CHECKING:
    from stages.models.bundle import Bundle

SCHEMA = "goi.batch"
#: The goi commands a scene's `options` may add to, in the order a scene runs them.
STAGES = ("extract", "init-codebook", "fit-field", "index-res", "query")
#: What a scene's name may be: one plain path component (it is OUT/<name>/ and a wildcard).
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}")
#: Option names of `options`: what goi's click options are made of.
_OPTION = re.compile(r"[a-z][a-z0-9-]*")
#: Options goi batch sets from a scene's keys and the batch's layout: not in `options`.
RESERVED = {
    "scene", "ply", "cameras", "images", "out", "from", "bundle", "features", "codebook",
    "field", "prompt", "prompt-id", "text-embeddings", "res-masks", "res-index", "lift",
    "part", "merge",  # index-res: the parts of index_jobs and their merge
}  # fmt: skip
#: A configuration is small: larger files, deeper nesting or more values are refused (YAML
#: aliases can make a small file a huge or endless tree).
MAX_BYTES = 16 << 20
MAX_DEPTH = 32
MAX_VALUES = 200_000


@dataclass
class Node:
    """A value of the file and the line it starts on (1-based)."""

    value: Any  # dict[str, Node] | list[Node] | str | int | float | bool | None
    line: int


def read_config(path: Path, what: str = "batch configuration") -> Node:
    """The file as a tree of Nodes; YAML or JSON, one key twice is refused."""
    import yaml

    text = read_text(path, what, MAX_BYTES)
    try:
        _bounded(text, path)  # before composing: PyYAML's composer recurses once per level
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise GoiError(f"{path}: not valid YAML or JSON{where}: {problem}") from None
    if root is None:
        raise GoiError(f"{path}: empty; a {what} is a YAML mapping")
    return _tree(root, path, [0], 0)


def _too_big(path: Path, line: int) -> GoiError:
    return GoiError(
        f"{path}: line {line}: nested deeper than {MAX_DEPTH} levels or more than "
        f"{MAX_VALUES} values (YAML aliases?); a batch configuration is a short list"
    )


def _bounded(text: str, path: Path) -> None:
    """Nesting and size from the parser's events, which come without recursion: a 5,000-deep
    `[[[...]]]` is refused here, not met by the composer's recursion. (Aliases are not
    expanded by the parser: `_tree` bounds what they make.)"""
    import yaml

    depth = events = 0
    for ev in yaml.parse(text, Loader=yaml.SafeLoader):
        events += 1
        if isinstance(ev, yaml.CollectionStartEvent):
            depth += 1
        elif isinstance(ev, yaml.CollectionEndEvent):
            depth -= 1
        if depth > MAX_DEPTH or events > MAX_VALUES:
            raise _too_big(path, ev.start_mark.line + 1)


def _tree(node: Any, path: Path, count: list[int], depth: int) -> Node:
    import yaml

    line = node.start_mark.line + 1
    count[0] += 1
    if depth > MAX_DEPTH or count[0] > MAX_VALUES:
        raise _too_big(path, line)
    if isinstance(node, yaml.MappingNode):
        out: dict[str, Node] = {}
        for k, v in node.value:
            key = _tree(k, path, count, depth + 1)
            if not isinstance(key.value, str):
                raise GoiError(f"{path}: line {key.line}: a key must be text, found {key.value!r}")
            if key.value in out:
                raise GoiError(
                    f"{path}: line {key.line}: key '{key.value}' appears twice in one mapping "
                    f"(first on line {out[key.value].line})"
                )
            out[key.value] = _tree(v, path, count, depth + 1)
        return Node(out, line)
    if isinstance(node, yaml.SequenceNode):
        return Node([_tree(v, path, count, depth + 1) for v in node.value], line)
    try:
        value = yaml.SafeLoader("").construct_object(node)  # a scalar, typed by YAML's rules
    except yaml.YAMLError as e:
        raise GoiError(f"{path}: line {line}: {getattr(e, 'problem', None) or e}") from None
    return Node(value, line)


class Checker:
    """Checks a tree against the schema's definitions, naming the key path and line."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.d = definition(SCHEMA)

    def fail(self, node: Node, key: str, message: str) -> GoiError:
        return GoiError(f"{self.path}: line {node.line}: '{key}' {message}")

    def fields(self, ref: str | dict) -> dict[str, dict]:
        spec = self.d["definitions"][ref] if isinstance(ref, str) else ref
        if isinstance(spec["fields"], str):  # a reference to a definition's fields
            return self.fields(spec["fields"])
        out = dict(spec["fields"])
        if "also" in spec:
            out.update(self.fields(spec["also"]))
        return out

    def obj(self, node: Node, key: str, spec: dict[str, dict]) -> dict[str, Node]:
        if not isinstance(node.value, dict):
            raise self.fail(node, key, f"should be a mapping, found {_kind(node.value)}")
        for name, child in node.value.items():
            if name not in spec:
                known = ", ".join(spec)
                where = f"'{key}.{name}'" if key else f"'{name}'"
                raise GoiError(
                    f"{self.path}: line {child.line}: unknown key {where} (known here: {known})"
                )
            self.value(child, f"{key}.{name}" if key else name, spec[name])
        for name, f in spec.items():
            if name not in node.value and not f.get("optional"):
                where = f"'{key}'" if key else "the file"
                raise GoiError(f"{self.path}: line {node.line}: {where} lacks the key '{name}'")
        return node.value

    def value(self, node: Node, key: str, f: dict) -> None:
        kinds = f["type"].split("|")
        v = node.value
        if isinstance(v, dict) and "object" in kinds:
            self.obj(node, key, self.fields(f))
        elif isinstance(v, dict) and "map" in kinds:
            self.options(node, key, f["keys"])
        elif isinstance(v, list) and "list" in kinds:
            items = self.d["definitions"][f["items"]]
            for i, item in enumerate(v):
                self.value(item, f"{key}[{i}]", items)
        elif isinstance(v, bool):
            if "bool" not in kinds:
                raise self.fail(node, key, f"should be {' or '.join(kinds)}, found {_kind(v)}")
        elif isinstance(v, str) and "str" in kinds:
            if not v.strip():
                raise self.fail(node, key, "is empty")
        elif isinstance(v, int | float) and "number" in kinds:
            pass
        else:
            raise self.fail(node, key, f"should be {' or '.join(kinds)}, found {_kind(v)}")

    def options(self, node: Node, key: str, stages: list[str]) -> None:
        for stage, opts in node.value.items():
            if stage not in stages:
                raise GoiError(
                    f"{self.path}: line {opts.line}: unknown key '{key}.{stage}' (known here: "
                    f"{', '.join(stages)})"
                )
            if not isinstance(opts.value, dict):
                raise self.fail(opts, f"{key}.{stage}", "should be a mapping {option: value}")
            for name, v in opts.value.items():
                where = f"{key}.{stage}.{name}"
                if not _OPTION.fullmatch(name):
                    raise self.fail(v, where, "is not an option name (e.g. iterations)")
                if name in RESERVED:
                    raise self.fail(
                        v, where, "is set by goi batch from the scene's keys and the batch's "
                        "layout; give it as a scene key, or leave it out"
                    )  # fmt: skip
                if isinstance(v.value, dict | list) or v.value is None:
                    raise self.fail(v, where, "should be a number, text, true or false")


def _kind(v: Any) -> str:
    names = {dict: "a mapping", list: "a list", str: "text", bool: "true/false"}
    return names.get(type(v), "nothing" if v is None else "a number")


@dataclass
class PromptJob:
    """One prompt of a scene: its answer's wildcard is the prompt's file name (`name`), and its
    id, when given, the subdirectory of res_masks (when it is not that name)."""

    prompt: Prompt
    masks: list[str] = field(default_factory=list)  # its RES mask files, when res_masks holds any


@dataclass
class SceneJob:
    """One scene of the batch, resolved: what the Snakefile runs for it."""

    name: str
    line: int
    scene_args: list[str]  # --scene DIR or --ply/--cameras/--images
    inputs: list[str]  # the files whose change reruns the scene (PLY, cameras)
    extract_args: list[str] | None  # None: the field-free route
    query_args: list[str]  # text, RES source, --lift
    index_bundle: str | None  # build OUT/<name>/res_index.h5 with this bundle
    options: dict[str, list[str]]  # stage -> its extra arguments
    #: (stage, option name) -> its line in the file and its value (checked by the CLI, which
    #: knows the commands' options)
    option_values: dict[tuple[str, str], tuple[int, Any]]
    prompts: list[PromptJob] = field(default_factory=list)
    #: more files whose change reruns a stage: the feature maps or the encoder's manifest
    #: (extract); the text embeddings, the bundle's manifest, a given RES index (query)
    extract_inputs: list[str] = field(default_factory=list)
    query_inputs: list[str] = field(default_factory=list)
    #: the index built as this many goi index-res jobs (parts), then merged
    index_parts: int = 1

    @property
    def fitted(self) -> bool:
        return self.extract_args is not None

    @property
    def index_jobs(self) -> int:
        """Jobs that build the index: one, or the parts and the merge."""
        if not self.index_bundle:
            return 0
        return 1 if self.index_parts == 1 else self.index_parts + 1


@dataclass
class Batch:
    config: Path
    out: Path
    scenes: list[SceneJob]

    def plan(self, python: str) -> dict[str, Any]:
        """What the Snakefile reads (its `config`)."""
        return {
            "python": python,
            "scenes": {
                s.name: {
                    "scene_args": s.scene_args,
                    "inputs": s.inputs,
                    "extract_inputs": s.extract_inputs,
                    "query_inputs": s.query_inputs,
                    "fitted": s.fitted,
                    "extract_args": s.extract_args or [],
                    "query_args": s.query_args,
                    "index_bundle": s.index_bundle,
                    "index_parts": s.index_parts,
                    # each part's onnxruntime threads: this machine's cores shared out
                    "index_threads": max(1, (os.cpu_count() or 1) // s.index_parts),
                    "options": s.options,
                    "prompts": {
                        p.prompt.name: {"text": p.prompt.text, "id": p.prompt.id, "masks": p.masks}
                        for p in s.prompts
                    },
                }
                for s in self.scenes
            },
        }


def load_batch(path: Path, out: Path | None = None) -> Batch:
    """The checked and resolved configuration: every scene found, every output distinct."""
    root = read_config(path)
    c = Checker(path)
    top = c.obj(root, "", c.d["fields"])
    if "schema" in top and top["schema"].value != SCHEMA:
        raise c.fail(top["schema"], "schema", f"should be {SCHEMA!r}")
    if "schema_version" in top:
        v, mine = str(top["schema_version"].value), current_version(SCHEMA)
        if v.split(".")[0] != mine.split(".")[0]:
            raise c.fail(
                top["schema_version"],
                "schema_version",
                f"{v} is not readable by this goi ({SCHEMA} {mine}): upgrade goi or rewrite "
                "the file for this version",
            )
    base = path.parent
    if out is None:
        given = Path(os.path.expanduser(top["out"].value)) if "out" in top else None
        out = base / given if given is not None else base / "goi-batch"
    defaults = top["defaults"].value if "defaults" in top else {}
    scenes_node = top["scenes"]
    if not scenes_node.value:
        raise c.fail(scenes_node, "scenes", "is empty; list at least one scene")
    scenes: list[SceneJob] = []
    seen: dict[str, SceneJob] = {}
    loaded = _Loaded()
    for i, node in enumerate(scenes_node.value):
        job = _scene(c, node, f"scenes[{i}]", defaults, base, loaded)
        other = seen.get(job.name.lower())  # case-insensitive file systems too
        if other is not None:
            raise GoiError(
                f"{path}: line {job.line}: scenes[{i}] and the scene on line {other.line} "
                f"both write {out / job.name}/; give one of them another 'name'"
            )
        seen[job.name.lower()] = job
        scenes.append(job)
    return Batch(path, out, scenes)


class _Loaded:
    """The inputs the stages' own checks read, each once per batch (a bundle, an embeddings
    table), so many scenes sharing one cost one check."""

    def __init__(self) -> None:
        self.bundles: dict[Path, Bundle] = {}
        self.tables: dict[Path, dict] = {}

    def indexable(self, path: Path) -> Bundle:
        key = path.resolve()
        if key not in self.bundles:
            self.bundles[key] = indexable_bundle(path, "'bundle'")
        return self.bundles[key]

    def embedding(self, path: Path, text: str) -> None:
        """The query's embedding of `text` is in the file (its own check, its own message)."""
        key = path.resolve()
        if key not in self.tables:
            self.tables[key] = load_text_embeddings(path)
        table = self.tables[key]
        if text not in table:
            text_embedding(text, next(iter(table.values())).size, path)  # raises, naming it
            raise AssertionError("text_embedding found a text the table lacks")

    def res_files(self, res_masks: Path, prompt: Prompt) -> list[str]:
        """The prompt's mask files, found as the query finds them (refused as it refuses)."""
        return _files(ResFiles(res_masks, prompt).dir, "*.png")


def _scene(
    c: Checker, node: Node, key: str, defaults: dict[str, Node], base: Path, loaded: _Loaded
) -> SceneJob:
    own: dict[str, Node] = node.value
    merged = {**defaults, **own}

    def get(name: str) -> Any:
        return merged[name].value if name in merged else None

    def where(name: str) -> Node:
        return merged.get(name, node)

    def local(name: str) -> Path | None:
        v = get(name)
        if v is None or isinstance(v, bool):
            return None
        p = Path(os.path.expanduser(v))
        return p if p.is_absolute() else base / p

    def exists(name: str) -> Path | None:
        p = local(name)
        if p is not None and not p.exists():
            raise c.fail(where(name), f"{key}.{name}", f"{p}: no such file or directory")
        return p

    scene_dir, ply, cameras, images = (exists(k) for k in ("scene", "ply", "cameras", "images"))
    if scene_dir is None and (ply is None or cameras is None):
        raise GoiError(
            f"{c.path}: line {node.line}: {key} names no scene: give 'scene' (a directory) or "
            "'ply' and 'cameras'"
        )
    try:
        scene = load_scene(scene_dir, ply, cameras, images)
    except GoiError as e:
        raise c.fail(where("scene" if scene_dir else "ply"), key, f"is not a scene: {e}") from None
    scene_args: list[str] = []
    for opt, p in (("--scene", scene_dir), ("--ply", ply), ("--cameras", cameras)):
        if p is not None:
            scene_args += [opt, str(p.resolve())]
    if images is not None:
        scene_args += ["--images", str(images.resolve())]
    name = get("name") or (scene_dir or scene.ply_path.parent).resolve().name
    if not _NAME.fullmatch(name):
        raise c.fail(
            where("name"), f"{key}.name", f"{name!r} is not a plain file name (letters, digits, "
            "'_', '-', '.', '+'; not starting with '.' or '-')"
        )  # fmt: skip

    features, feature_bundle = exists("features"), exists("feature_bundle")
    if features is not None and feature_bundle is not None:
        raise c.fail(where("feature_bundle"), key, "gives both 'features' and 'feature_bundle'")
    extract_args = None
    if features is not None:
        extract_args = ["--from", str(features.resolve())]
    elif feature_bundle is not None:
        extract_args = ["--bundle", str(feature_bundle.resolve())]

    query_args: list[str] = []
    for k, opt in (("text_embeddings", "--text-embeddings"), ("bundle", "--bundle")):
        p = exists(k)
        if p is not None:
            query_args += [opt, str(p.resolve())]
    res_masks, bundle = exists("res_masks"), local("bundle")
    if res_masks is not None:
        query_args += ["--res-masks", str(res_masks.resolve())]
    index_bundle = None
    res_index = get("res_index")
    if res_index is True:
        if bundle is None:
            raise c.fail(where("res_index"), f"{key}.res_index", "is true but no 'bundle' is given")
        index_bundle = str(bundle.resolve())
        try:  # what goi index-res checks first: a bundle with an image side, every photo
            loaded.indexable(bundle)
            for cam in scene.views("train"):
                scene.image_path(cam)  # raises, naming a photo that is not there
        except GoiError as e:
            raise c.fail(where("res_index"), f"{key}.res_index", f"cannot be built: {e}") from None
    index_parts = get("index_jobs")
    if index_parts is not None:
        if index_bundle is None:
            raise c.fail(where("index_jobs"), f"{key}.index_jobs", "is given but 'res_index' is "
                         "not true (goi batch builds no index to split)")  # fmt: skip
        if not isinstance(index_parts, int) or not 1 <= index_parts <= 256:
            raise c.fail(where("index_jobs"), f"{key}.index_jobs", "should be a whole number "
                         "from 1 to 256")  # fmt: skip
        n_train = len(scene.views("train"))
        if index_parts > n_train:
            raise c.fail(where("index_jobs"), f"{key}.index_jobs", f"is {index_parts}, but the "
                         f"scene has {n_train} training views to share out")  # fmt: skip
    if isinstance(res_index, str):
        index = exists("res_index")
        assert index is not None
        try:  # the query's own check: this scene's views and images, this bundle
            if res_masks is not None:
                raise GoiError("'res_masks' is given too; a query reads one RES source")
            checked_index(index, loaded.indexable(bundle) if bundle else None, scene)
        except GoiError as e:
            raise c.fail(where("res_index"), f"{key}.res_index", f"cannot be used: {e}") from None
        query_args += ["--res-index", str(index.resolve())]
    lift = bool(get("lift"))
    if lift:
        query_args.append("--lift")
    if extract_args is None and not (lift and (res_masks is not None or bundle is not None)):
        raise GoiError(
            f"{c.path}: line {node.line}: {key} has no features source ('features' or "
            "'feature_bundle'), so it goes the field-free route, which needs 'lift: true' and a "
            "RES source ('res_masks' or 'bundle')"
        )

    options: dict[str, list[str]] = {}
    option_values: dict[tuple[str, str], tuple[int, Any]] = {}
    for stage in STAGES:
        merged_opts: dict[str, Node] = {}
        for source in (defaults, own):
            if "options" in source and stage in source["options"].value:
                merged_opts.update(source["options"].value[stage].value)
        options[stage] = _args(merged_opts)
        option_values.update({(stage, k): (v.line, v.value) for k, v in merged_opts.items()})

    prompts_node = merged.get("prompts")
    if prompts_node is None or not prompts_node.value:
        raise GoiError(f"{c.path}: line {node.line}: {key} has no prompts (here or in defaults)")
    pkey = f"{key}.prompts" if "prompts" in own else "defaults.prompts"
    embeddings = local("text_embeddings")
    if extract_args is not None and embeddings is None and bundle is None:
        raise GoiError(
            f"{c.path}: line {node.line}: {key} goes the paper's route, whose queries need each "
            "prompt's text embedding: give 'text_embeddings' or a 'bundle' with a text encoder"
        )
    prompts: list[PromptJob] = []
    by_key: dict[str, int] = {}
    for i, p in enumerate(prompts_node.value):
        raw, pid = (p.value, None) if isinstance(p.value, str) else _prompt(p)
        at = f"{c.path}: line {p.line}: '{pkey}[{i}]'"
        # What goi query does with the text and the id, so the answer lands where the
        # workflow expects it (`goi query` strips the text before it names the answer).
        text = check_prompt(raw, at)
        if pid is not None:
            at_id = f"{c.path}: line {p.line}: '{pkey}[{i}].id'"
            check_plain_name(pid, at_id, "a subdirectory of 'res_masks'")
        prompt = Prompt(text, pid)
        k = prompt.name
        if k in by_key:
            raise GoiError(
                f"{c.path}: line {p.line}: {key}: the prompt {text!r} is given twice (also on "
                f"line {by_key[k]}); both would write the same answer"
            )
        by_key[k] = p.line
        try:
            if extract_args is not None and embeddings is not None:
                loaded.embedding(embeddings, text)
            masks = loaded.res_files(res_masks, prompt) if res_masks is not None else []
        except GoiError as e:
            raise GoiError(f"{at}: {e}") from None
        prompts.append(PromptJob(prompt, masks))

    def literal(name: str, files: list[str]) -> list[str]:
        """Files the workflow lists as inputs, which Snakemake reads as patterns: `{x}` in a
        path would be a wildcard (its patterns have no escape), so such a path is refused."""
        from snakemake_interface_storage_plugins.io import WILDCARD_REGEX

        for f in files:
            m = WILDCARD_REGEX.search(f)
            if m is not None:
                raise c.fail(
                    where(name), f"{key}.{name}", f"{f}: Snakemake would read {m.group(0)!r} "
                    "in this path as a wildcard; rename it (or link it) without braces"
                )  # fmt: skip
        return files

    scene_files = [scene.ply_path, *scene.camera_files]
    inputs = literal("scene" if scene_dir else "ply", [str(f.resolve()) for f in scene_files])
    extract_inputs = literal("features", [*_files(features, "*.npy"), *_files(features, "*.pt")])
    extract_inputs += literal("feature_bundle", _files(feature_bundle, "manifest.json"))
    query_inputs = literal("bundle", _files(bundle, "manifest.json"))
    for k in ("text_embeddings", "res_index"):
        p = local(k)
        if p is not None and p.is_file():
            query_inputs += literal(k, [str(p.resolve())])
    for job in prompts:
        literal("res_masks", job.masks)
    return SceneJob(
        name, node.line, scene_args, inputs, extract_args, query_args, index_bundle, options,
        option_values, prompts, extract_inputs, query_inputs, index_parts or 1,
    )  # fmt: skip


def _files(directory: Path | None, pattern: str) -> list[str]:
    """The files of `directory` matching `pattern` (none when it is not a directory)."""
    if directory is None or not directory.is_dir():
        return []
    return sorted(str(f.resolve()) for f in directory.glob(pattern) if f.is_file())


def _prompt(p: Node) -> tuple[str, str | None]:
    d = p.value
    return d["text"].value, (str(d["id"].value) if "id" in d else None)


def _args(opts: dict[str, Node]) -> list[str]:
    """{option: value} as command-line arguments: true is a flag, false leaves it out."""
    out: list[str] = []
    for name, v in opts.items():
        if v.value is True:
            out.append(f"--{name}")
        elif v.value is not False:
            out += [f"--{name}", str(v.value)]
    return out
