"""Versioned artifact schemas and the validator every reader goes through.

One JSON definition per artifact lives beside this file (`<schema name>.json`). A definition
lists the root attributes, groups and datasets the artifact holds, with dtypes and shapes. Shape
entries are integers or symbols: an upper-case symbol (``G``) must take the same value everywhere
in the file, or equal the root attribute of that name when there is one; a lower-case symbol
(``nnz``) is bound separately inside each instance of a ``{placeholder}`` group.

Versions are ``major.minor``. A reader accepts any minor version of the major it knows (minor
versions only add optional content) and refuses other majors with a message saying what to do.
"""

from __future__ import annotations

import json
import os
import re
from functools import cache
from importlib import resources
from typing import Any

import h5py
import numpy as np

from stages.core.errors import GoiError
from stages.core.hdf5 import read_h5

PROVENANCE_ATTRS = ("goi_version", "command", "created", "inputs")
#: A dataset declaring more than this is refused before anything is read: HDF5 can declare a
#: huge, unallocated dataset in a tiny file, and reading it would allocate all of it.
MAX_DATASET_BYTES = 8 << 30

_PLACEHOLDER = re.compile(r"\{(\w+)\}")


@cache
def definition(schema: str) -> dict[str, Any]:
    name = f"{schema}.json"
    try:
        text = resources.files("schemas").joinpath(name).read_text()
    except FileNotFoundError:
        raise GoiError(f"unknown artifact schema {schema!r}") from None
    return json.loads(text)


def known_schemas() -> list[str]:
    """The HDF5 artifact schemas (JSON documents such as bundle manifests are not among them)."""
    return sorted(
        p.name[: -len(".json")]
        for p in resources.files("schemas").iterdir()
        if p.name.startswith("goi.")
        and p.name.endswith(".json")
        and json.loads(p.read_text()).get("kind", "hdf5") == "hdf5"
    )


def current_version(schema: str) -> str:
    return str(definition(schema)["version"])


def _major(version: str) -> int:
    try:
        return int(str(version).split(".")[0])
    except ValueError:
        return -1


def _expand(f: h5py.File, pattern: str) -> list[tuple[str, tuple[str, ...]]]:
    """All paths in `f` matching `pattern`, with the values its placeholders took."""
    parts = pattern.split("/")
    found: list[tuple[str, tuple[str, ...]]] = [("", ())]
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        nxt: list[tuple[str, tuple[str, ...]]] = []
        for prefix, binding in found:
            if prefix.endswith("\0missing"):  # below a missing group: missing too
                nxt.append((prefix[: -len("\0missing")] + f"/{part}\0missing", binding))
                continue
            parent = f[prefix] if prefix else f
            if not isinstance(parent, h5py.Group):
                continue
            if _PLACEHOLDER.fullmatch(part):
                for key in parent:
                    if last or isinstance(parent[key], h5py.Group):
                        nxt.append((f"{prefix}/{key}".lstrip("/"), (*binding, key)))
            elif part in parent:
                nxt.append((f"{prefix}/{part}".lstrip("/"), binding))
            else:
                # Report a missing fixed path once, through the caller.
                nxt.append((f"{prefix}/{part}".lstrip("/") + "\0missing", binding))
        found = nxt
    return found


_DTYPE_KINDS = {"float": "f", "int": "iu", "str": "OSU", "bool": "b"}


def _check_attr(errors: list[str], where: str, attrs: Any, name: str, kind: str) -> None:
    if name not in attrs:
        errors.append(f"{where}: attribute '{name}' is missing")
        return
    value = np.asarray(attrs[name])
    if kind == "json":
        try:
            json.loads(value.item() if value.ndim == 0 else "")
        except (ValueError, TypeError, AttributeError):
            errors.append(f"{where}: attribute '{name}' is not a JSON string")
        return
    if value.dtype.kind not in _DTYPE_KINDS[kind]:
        errors.append(f"{where}: attribute '{name}' should be {kind}, found {value.dtype}")


def _validate_open(f: h5py.File, expected: str | None) -> tuple[list[str], str]:
    errors: list[str] = []
    schema = f.attrs.get("schema")
    if isinstance(schema, bytes):
        schema = schema.decode()
    if not isinstance(schema, str):
        return ["root attribute 'schema' is missing: not a goi artifact"], ""
    if expected is not None and schema != expected:
        return [f"holds a {schema} artifact, but a {expected} artifact is needed here"], schema
    if schema not in known_schemas():
        return [f"unknown schema {schema!r} (this goi knows {', '.join(known_schemas())})"], schema
    version = str(f.attrs.get("schema_version", ""))
    ours = current_version(schema)
    if _major(version) != _major(ours):
        hint = (
            "upgrade goi to read it, or re-create it with this goi"
            if _major(version) > _major(ours)
            else "re-create it with this goi"
        )
        return [
            f"{schema} version {version or '?'} is not readable by goi's {ours}: {hint}"
        ], schema
    d = definition(schema)
    for name in PROVENANCE_ATTRS:
        _check_attr(errors, "/", f.attrs, name, "json" if name == "inputs" else "str")
    for name, kind in d.get("attrs", {}).items():
        _check_attr(errors, "/", f.attrs, name, kind)
    global_dims: dict[str, int] = {
        k: int(v)
        for k, v in f.attrs.items()
        if np.asarray(v).dtype.kind in "iu" and np.ndim(v) == 0
    }
    for pattern, spec in d.get("groups", {}).items():
        for path, _ in _expand(f, pattern):
            if path.endswith("\0missing"):
                if not spec.get("optional"):
                    errors.append(f"group '{path[:-8]}' is missing")
                continue
            if not isinstance(f[path], h5py.Group):
                errors.append(f"'{path}' should be a group")
                continue
            for name, kind in spec.get("attrs", {}).items():
                _check_attr(errors, path, f[path].attrs, name, kind)
    local_dims: dict[tuple[str, ...], dict[str, int]] = {}
    for pattern, spec in d.get("datasets", {}).items():
        for path, binding in _expand(f, pattern):
            if path.endswith("\0missing"):
                if not spec.get("optional"):
                    errors.append(f"dataset '{path[:-8]}' is missing")
                continue
            ds = f[path]
            if not isinstance(ds, h5py.Dataset):
                errors.append(f"'{path}' should be a dataset")
                continue
            if ds.size * ds.dtype.itemsize > MAX_DATASET_BYTES:
                errors.append(
                    f"dataset '{path}' declares {ds.shape} ({ds.size * ds.dtype.itemsize:.3g} "
                    f"bytes), more than goi reads ({MAX_DATASET_BYTES >> 30} GiB)"
                )
                continue
            want = spec["dtype"]
            got = ds.dtype
            ok = (got.kind in "OSU") if want == "str" else got == np.dtype(want)
            if not ok:
                errors.append(f"dataset '{path}' has dtype {got}, expected {want}")
            shape = spec.get("shape")
            if shape is None:
                continue
            if len(shape) != ds.ndim:
                errors.append(
                    f"dataset '{path}' has {ds.ndim} dimensions {ds.shape}, expected {len(shape)}"
                )
                continue
            scope = local_dims.setdefault(binding, {})
            for axis, (sym, n) in enumerate(zip(shape, ds.shape, strict=True)):
                if isinstance(sym, int):
                    if n != sym:
                        errors.append(f"dataset '{path}' axis {axis} has size {n}, expected {sym}")
                    continue
                table = global_dims if (sym[0].isupper() or sym in global_dims) else scope
                if sym in table and table[sym] != n:
                    errors.append(
                        f"dataset '{path}' axis {axis} has size {n}, "
                        f"but {sym} = {table[sym]} elsewhere"
                    )
                table.setdefault(sym, n)
    return errors, schema


def validate_file(
    path: str | os.PathLike[str], expected: str | None = None, raise_on_error: bool = False
) -> tuple[str, list[str]]:
    """Validate an HDF5 artifact; returns (schema name, list of problems)."""
    p = os.fspath(path)
    if not os.path.isfile(p):
        errors, schema = ["no such file"], ""
    else:
        try:
            with read_h5(p) as f:
                errors, schema = _validate_open(f, expected)
        except (OSError, KeyError, ValueError, RuntimeError, TypeError) as e:
            # h5py reports damaged metadata with any of these
            errors, schema = [f"not a readable HDF5 file ({str(e)[:200]})"], ""
    if errors and raise_on_error:
        more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
        raise GoiError(f"{p}: {errors[0]}{more}")
    return schema, errors


_JSON_TYPES: dict[str, type | tuple[type, ...]] = {
    "str": str,
    "int": int,
    "list": list,
    "object": dict,
    "float": (int, float),
}


def validate_json(obj: Any, schema: str, where: str) -> None:
    """Check a JSON document (e.g. a bundle manifest) against its definition; raise GoiError
    naming the file and the field."""
    d = definition(schema)
    if not isinstance(obj, dict):
        raise GoiError(f"{where}: expected a JSON object")
    if obj.get("schema") != schema:
        raise GoiError(f"{where}: field 'schema' should be {schema!r}, found {obj.get('schema')!r}")
    version = str(obj.get("schema_version", ""))
    if _major(version) != _major(d["version"]):
        raise GoiError(
            f"{where}: {schema} version {version or '?'} is not readable by goi's "
            f"{d['version']}: upgrade goi or re-create the file"
        )
    _check_fields(obj, d["fields"], where, "")


def _check_fields(obj: dict, spec: dict, where: str, prefix: str) -> None:
    for name, f in spec.items():
        key = f"{prefix}{name}"
        if name not in obj:
            if not f.get("optional"):
                raise GoiError(f"{where}: field '{key}' is missing")
            continue
        value = obj[name]
        kind = _JSON_TYPES[f["type"]]
        if not isinstance(value, kind) or isinstance(value, bool):
            raise GoiError(
                f"{where}: field '{key}' should be {f['type']}, found {type(value).__name__}"
            )
        if isinstance(value, dict):
            _check_fields(value, f.get("fields", {}), where, key + ".")
