"""pydantic's validation errors as the framework's one-line config errors.

`validated(cls, values, prefix)` builds a config dataclass (pydantic-validated, stm.config.STRICT)
from a section of a profile; its first error becomes a `ConfigError` like
"train.iters: expected an integer, got 'abc'" or "eval.feedback: 'x' is not allowed; allowed:
sample, component_mean, mixture_mean" -- the field's full dotted name, what is allowed.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import re
import typing
from typing import Any

from pydantic import BaseModel, ValidationError, create_model

from stm.config import STRICT


class ConfigError(ValueError):
    """A bad config value; str() is the one-line message shown to the user."""


def as_tuple(value: Any) -> Any:
    """A list field given one value (`--set eval.circle_radii=0.05`) is a list of one."""
    return (value,) if isinstance(value, (str, int, float)) else value


def tuples(x: Any) -> Any:
    """TOML and JSON lists as tuples (strict validation types list fields as tuples)."""
    if isinstance(x, dict):
        return {k: tuples(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return tuple(tuples(v) for v in x)
    return x


def validated(cls: type, values: dict[str, Any], prefix: str, hidden: tuple[str, ...] = ()) -> Any:
    """cls(**values), or a ConfigError naming `prefix.field` (hidden: fields not to list as allowed)."""
    try:
        return cls(**tuples(values))
    except ValidationError as e:
        names = cls.model_fields if isinstance(cls, type) and issubclass(cls, BaseModel) else \
            [f.name for f in dataclasses.fields(cls)]
        allowed = [n for n in names if n not in hidden]
        raise ConfigError(message(e, prefix, allowed)) from None


_EXPECTED = {
    "int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer",
    "float_type": "a number", "float_parsing": "a number", "bool_type": "true or false",
    "bool_parsing": "true or false", "string_type": "a string", "tuple_type": "a list", "list_type": "a list",
    "dict_type": "a section of FIELD = VALUE", "dataclass_type": "a section of FIELD = VALUE",
    "dataclass_exact_type": "a section of FIELD = VALUE",
}
_BOUNDS = {"greater_than_equal": ">=", "greater_than": ">", "less_than_equal": "<=", "less_than": "<"}
_BOUND_KEYS = {"greater_than_equal": "ge", "greater_than": "gt", "less_than_equal": "le", "less_than": "lt"}


def message(err: ValidationError, prefix: str, allowed_fields: list[str]) -> str:
    """The first error of `err` in one line: '<prefix.field>: <what is wrong>; allowed: <...>'."""
    e = err.errors(include_url=False)[0]
    loc = [str(p) for p in e["loc"] if not isinstance(p, int)]
    name = ".".join(p for p in (prefix, *loc) if p)
    kind, value, ctx = e["type"], e.get("input"), e.get("ctx") or {}
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        return f"{name}: unknown field; allowed: {', '.join(allowed_fields)}"
    if kind in _EXPECTED:
        return f"{name}: expected {_EXPECTED[kind]}, got {value!r}"
    if kind == "literal_error":
        choices = re.findall(r"'([^']*)'", str(ctx.get("expected", "")))
        return f"{name}: {value!r} is not allowed; allowed: {', '.join(choices)}"
    if kind in _BOUNDS:
        bound = ctx[_BOUND_KEYS[kind]]
        what = "integers" if isinstance(bound, int) else "numbers"  # float fields have float bounds
        return f"{name}: {value!r} is not allowed; allowed: {what} {_BOUNDS[kind]} {bound:g}"
    if kind == "finite_number":
        return f"{name}: {value!r} is not allowed; allowed: finite numbers"
    if kind == "value_error":  # a validator's own message (the checks of the config classes)
        text = str(e["msg"]).removeprefix("Value error, ").splitlines()[0]
        return f"{name}: {text}" if name else text
    return f"{name}: {str(e['msg']).splitlines()[0]}"


def signature_model(task: str) -> type:
    """A pydantic model of a task constructor's keyword arguments (name, type, default)."""
    from envs.tasks import task_class

    return _options_model(task_class(task))


@functools.cache  # per class: a task registered again under the same name gets its own
def _options_model(cls: type) -> type:
    hints = typing.get_type_hints(cls.__init__)
    params = [p for p in inspect.signature(cls.__init__).parameters.values() if p.name != "self"]
    fields = {p.name: (hints.get(p.name, Any), p.default if p.default is not inspect.Parameter.empty else ...)
              for p in params}
    return create_model(f"{cls.__name__}Options", __config__=STRICT, **fields)
