"""Click options generated from a stage's options dataclass, so each option is defined once:
its name, type, default and help all come from the dataclass field and its docstring."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from stages.core.params import Range, field_choice, field_range

if TYPE_CHECKING:
    from stages.scene.scene import Scene


def field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each field of a dataclass."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for a, b in zip(body, body[1:], strict=False):
        if (
            isinstance(a, ast.AnnAssign)
            and isinstance(a.target, ast.Name)
            and isinstance(b, ast.Expr)
            and isinstance(b.value, ast.Constant)
            and isinstance(b.value.value, str)
        ):
            docs[a.target.id] = " ".join(b.value.value.split())
    return docs


def _base_type(tp: Any) -> Any:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0]
    return tp


class Number(click.ParamType):
    """An int or float option checked against its field's Range while parsing; floats must be
    finite (click's own FloatRange lets NaN through)."""

    def __init__(self, base: type, rng: Range | None):
        self.base = click.INT if base is int else click.FLOAT
        self.rng = rng or Range()
        self.name = self.base.name

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        v = self.base.convert(value, param, ctx)
        why = self.rng.problem(v)
        if why:
            self.fail(why, param, ctx)
        return v


def dataclass_options(cls: type, skip: tuple[str, ...] = ()) -> Callable:
    """Decorate a command with one option per field of `cls` (snake_case -> --kebab-case)."""
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)

    def decorate(fn: Callable) -> Callable:
        for f in reversed(dataclasses.fields(cls)):
            if f.name in skip:
                continue
            flag = "--" + f.name.replace("_", "-")
            tp = _base_type(hints[f.name])
            required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
            default = None if required else f.default
            help_ = docs.get(f.name, "")
            rng = field_range(cls, f.name)
            if rng is not None:
                help_ += f" Range: {rng.describe()}."
            choice = field_choice(cls, f.name)
            if tp is bool and default is True:  # on by default: --x/--no-x
                off = "--no-" + f.name.replace("_", "-")
                fn = click.option(f"{flag}/{off}", f.name, default=True, help=help_)(fn)
            elif tp is bool:
                fn = click.option(flag, f.name, is_flag=True, default=default, help=help_)(fn)
            elif tp is Path:
                fn = click.option(
                    flag,
                    f.name,
                    type=click.Path(path_type=Path),
                    required=required,
                    default=default,
                    show_default=default is not None,
                    help=help_,
                )(fn)
            else:
                fn = click.option(
                    flag,
                    f.name,
                    type=(
                        Number(tp, rng)
                        if tp in (int, float)
                        else click.Choice(choice.values)
                        if choice
                        else tp
                    ),
                    required=required,
                    default=default,
                    show_default=True,
                    help=help_,
                )(fn)
        return fn

    return decorate


#: An existing file (click checks it before the command runs).
EXISTING = click.Path(exists=True, dir_okay=False, path_type=Path)


def build(cls: type, kwargs: dict[str, Any]) -> Any:
    """The options object from the parsed keyword arguments (removing them from kwargs)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: kwargs.pop(k) for k in list(kwargs) if k in names})


def stack(*opts: Callable) -> Callable:
    """One decorator applying several click options, in the order given."""

    def deco(fn: Callable) -> Callable:
        for o in reversed(opts):
            fn = o(fn)
        return fn

    return deco


def path_option(flag: str, help: str, *names: str, **kw: Any) -> Callable:
    """An option naming a file or directory, checked by the stage (whose errors name it)."""
    return click.option(flag, *names, type=click.Path(path_type=Path), help=help, **kw)


#: --scene DIR, or explicit --ply/--cameras/--images (they override the directory's).
scene_options = stack(
    path_option(
        "--scene",
        "Scene directory: point_cloud.ply, cameras (cameras.json, transforms*.json or sparse/), "
        "images/, split.json.",
    ),
    path_option("--ply", "The 3DGS PLY (INRIA layout), instead of the scene's."),
    path_option("--cameras", "cameras.json, transforms*.json or a COLMAP model directory."),
    path_option("--images", "Directory of the training images."),
)
features_option = click.option(
    "--features", type=EXISTING, required=True, help="Features artifact (goi extract)."
)


def load_scene_from(kwargs: dict[str, Any]) -> Scene:
    """The scene named by scene_options (removing those options from kwargs)."""
    from stages.scene.scene import load_scene

    return load_scene(
        kwargs.pop("scene"), kwargs.pop("ply"), kwargs.pop("cameras"), kwargs.pop("images")
    )
