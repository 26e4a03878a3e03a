"""What every socnav setting shares, below the simulator and everything else: the strict base model, the bounded
YAML and JSON reader of a mapping, the deep merge, and the one formatter of validation errors (each names the
field and what is allowed, with a did-you-mean).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Union

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    ValidationError,
)

# YAML input is bounded by `socnav.io` (the lowest layer: the simulator's map reader uses it too); re-exported here.
from socnav.io import YAML_MAX_BYTES as YAML_MAX_BYTES
from socnav.io import YAML_MAX_DEPTH as YAML_MAX_DEPTH
from socnav.io import YAML_MAX_NODES as YAML_MAX_NODES
from socnav.io import YAMLTooLargeError as YAMLTooLargeError
from socnav.io import file_size_problem as file_size_problem
from socnav.io import read_yaml_file as read_yaml_file
from socnav.io import safe_load_yaml as safe_load_yaml
from socnav.io import yaml_problem as yaml_problem


class ConfigError(ValueError):
    """A configuration value is wrong; the message names the field and what is allowed."""


def read_mapping_file(path: str | Path, what: str, error: type[Exception] = ConfigError,
                      allow_json: bool = False) -> dict[str, Any]:
    """The mapping of fields a YAML file holds (an empty file is an empty mapping), read with the bounded loader;
    with `allow_json` a ``.json`` file is read as JSON (which writes inf as ``Infinity``, unlike YAML), bounded in
    nesting (`socnav.io.parse_json`).

    :raises error: one line naming the file: '<what> file not found: PATH', '<what> file PATH is a directory, not a
        file', '<what> file PATH is not valid YAML: ...' (or '... is refused: ...' for an oversized, deeply nested or
        binary input, or an integer of thousands of digits), '<what> file PATH must hold a mapping of fields, got list'.
    """
    from socnav.io import UntrustedInputError, parse_json, read_bounded

    path = Path(path)
    if path.is_dir():
        raise error(f"{what} file {path} is a directory, not a file")
    if not path.exists():
        raise error(f"{what} file not found: {path}")
    too_large = file_size_problem(path, YAML_MAX_BYTES)  # from the size: a sparse 1 TB file costs nothing
    if too_large:
        raise error(f"{what} file {path} {too_large}")
    try:
        # Read within the limit whatever the filesystem reports (a /proc file claims 0 bytes), never a device or pipe.
        raw = read_bounded(path, YAML_MAX_BYTES)
        if allow_json and path.suffix == ".json":
            data = parse_json(raw, f"{what} file {path}")
        else:
            data = safe_load_yaml(raw.decode())
    except OSError as exc:
        raise error(f"{what} file {path} cannot be read: {exc.strerror or exc}") from None
    except UntrustedInputError as exc:
        message = str(exc)
        raise error(message if message.startswith(what) else f"{what} file {message}") from None
    except UnicodeDecodeError:
        raise error(f"{what} file {path} is refused: it is not UTF-8 text (a binary file?)") from None
    except yaml.YAMLError as exc:
        raise error(f"{what} file {path} {' '.join(yaml_problem(exc).split())}") from None
    except ValueError as exc:  # a value YAML parses but Python will not build, e.g. an integer of 5,000 digits
        import sys

        digits = sys.get_int_max_str_digits()
        reason = (f"it holds an integer of more than {digits:,} digits" if "integer string conversion" in str(exc)
                  else " ".join(str(exc).split())[:200])
        raise error(f"{what} file {path} is refused: {reason}") from None
    if data is None:  # an empty file (or only comments)
        return {}
    if not isinstance(data, dict):
        raise error(f"{what} file {path} must hold a mapping of fields, got {type(data).__name__}")
    return data


def short_repr(value: Any, limit: int = 200) -> str:
    """A repr for error messages of at most `limit` characters; `reprlib` elides the inside of large containers
    without building their full repr, so a huge input costs nothing to report."""
    import reprlib

    shortener = reprlib.Repr()
    shortener.maxstring = shortener.maxother = limit
    text = shortener.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class StrictModel(BaseModel):
    """Base of socnav's validated settings (env, experiments, thresholds, hyperparameters): unknown fields are
    rejected and every float must be finite (NaN and +-inf are refused by pydantic with the field named). Counts
    are declared ``StrictInt``, so ``true`` is not read as 1 and ``2.5`` is not truncated."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


#: Fields that were renamed: an old name in a file gets "renamed: write <new name>" instead of "unknown field".
RENAMED_FIELDS: dict[str, str] = {"dropout_p": "p_train"}  # the paper's name (Table I)


#: Allowed names are listed in full up to this many; a longer list is only worth reading when nothing is close.
_SHORT_LIST = 8


def close_names(name: str, allowed: Sequence[str]) -> list[str]:
    """The allowed names closest to `name`, best first (difflib, ignoring case; at most 3): every did-you-mean of
    socnav."""
    import difflib

    by_lower = {option.lower(): option for option in allowed}
    return [by_lower[match] for match in difflib.get_close_matches(name.lower(), list(by_lower), n=3, cutoff=0.6)]


def unknown_name_message(what: str, name: Any, allowed: Sequence[str]) -> str:
    """The message for a value that must be one of the registered names `allowed`, e.g. unknown human model
    'socail_force'; allowed: orca, social_force; did you mean social_force? (the validation error names the field)."""
    close = close_names(name, allowed) if isinstance(name, str) else []
    message = f"unknown {what} {short_repr(name)}; allowed: {', '.join(allowed)}"
    return f"{message}; did you mean {' or '.join(close)}?" if close else message


def unknown_field_message(name: str, allowed: Sequence[str]) -> str:
    """'unknown field; allowed fields: a, b, c; did you mean b?' (difflib's closest allowed names). A long list of
    allowed names is left out when a close one exists (not what a user with a typo wants to read)."""
    allowed = list(allowed)
    if RENAMED_FIELDS.get(name) in allowed:
        return f"renamed: write {RENAMED_FIELDS[name]} ({name} is its old name)"
    close = close_names(name, allowed)
    hint = f"did you mean {' or '.join(close)}?"
    if close and len(allowed) > _SHORT_LIST:
        return f"unknown field; {hint}"
    listing = f"unknown field; allowed fields: {', '.join(allowed)}"
    return f"{listing}; {hint}" if close else listing


def format_validation_error(error: ValidationError, headline: str, model: type[BaseModel]) -> str:
    """socnav's one message for a pydantic error of `model`: `headline`, then a line per problem naming the field
    path, what is wrong with the allowed values, and the bad value (capped: see `short_repr`)::

        invalid socnav config (env.yaml):
          - reward.gaol: unknown field; allowed fields: goal, collision, ...; did you mean goal?
          - time_step: Input should be less than or equal to 1 (got 5)
    """
    lines = [headline]
    for item in error.errors():
        loc = tuple(item["loc"])
        parent = _model_at(model, loc[:-1])
        if item["type"] == "extra_forbidden":
            message = (unknown_field_message(str(loc[-1]), list(parent.model_fields)) if parent is not None
                       else "unknown field")
        elif item["type"] == "missing":
            required = [name for name, info in parent.model_fields.items() if info.is_required()] if parent else []
            message = "required field is missing" + (f" (required here: {', '.join(required)})" if required else "")
        else:
            message = item["msg"].removeprefix("Value error, ")
        got = "" if item["type"] == "missing" else f" (got {short_repr(item.get('input'))})"
        lines.append(f"  - {'.'.join(str(part) for part in loc) or '<root>'}: {message}{got}")
    return "\n".join(lines)


def _model_at(model: type[BaseModel], loc: Sequence[Any]) -> type[BaseModel] | None:
    """The model holding the fields at `loc` inside `model` (through nested models, Optional and dict values)."""
    import types
    import typing

    def plain(annotation: Any) -> Any:  # Optional[X] -> X
        if typing.get_origin(annotation) in (Union, types.UnionType):
            members = [arg for arg in typing.get_args(annotation) if arg is not type(None)]
            return members[0] if len(members) == 1 else annotation
        return annotation

    current: Any = model
    for part in loc:
        if isinstance(current, type) and issubclass(current, BaseModel):
            info = current.model_fields.get(str(part))
            current = None if info is None else plain(info.annotation)
        elif typing.get_origin(current) is dict:  # `part` is a key, e.g. budgets.<name>
            current = plain(typing.get_args(current)[1])
        else:
            return None
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None


def deep_merge(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    """`base` updated with `extra`, nested mappings merged key by key (neither input is modified)."""
    merged = dict(base)
    for key, value in extra.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged

