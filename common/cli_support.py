"""What the `gmt` commands share: options generated from the configuration they fill, and extras checks.

A command's options are made from the fields of the dataclass (or pydantic settings) it fills: the flag's default
is the field's default and its help the field's line under `Attributes:` in the class docstring, so neither can
drift from the configuration. `needs(extra)` makes a command say which extra to install when it is missing.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import re
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, Optional, Union

import typer

from gmt.common.extras import MissingExtra, require

_ATTR = re.compile(r"^(\s*)(\w+):\s*(.*)$")


@dataclass(frozen=True)
class Flag:
    """One generated option.

    Attributes:
        field: The configuration field it fills (also the command's keyword argument).
        decls: Option names, e.g. ("--warmup-steps", "--warmup") or ("--bf16/--no-bf16",).
        annotation: The option's type as typer reads it.
        default: The option's default (None for settings: unset flags leave the environment's value).
        config_default: The configuration's default for the field.
        help: The help text.
    """

    field: str
    decls: tuple[str, ...]
    annotation: Any
    default: Any
    config_default: Any
    help: str

    def parameter(self) -> inspect.Parameter:
        """The typer parameter."""
        shown: Any = True
        if self.default is None and self.config_default is not None:
            shown = _show(self.config_default)
        option = typer.Option(self.default, *self.decls, help=self.help, show_default=shown)
        return inspect.Parameter(
            self.field, inspect.Parameter.KEYWORD_ONLY, default=option, annotation=self.annotation
        )


def _show(value: Any) -> str:
    if isinstance(value, list | tuple):
        return ", ".join(str(v) for v in value)
    return str(value)


def field_docs(cls: type) -> dict[str, str]:
    """{field: text} from the `Attributes:` sections of `cls`'s docstring and its bases' (continuation lines joined)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        lines = inspect.cleandoc(klass.__dict__.get("__doc__") or "").splitlines()
        try:
            start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes:") + 1
        except StopIteration:
            continue
        name, indent = None, None
        for line in lines[start:]:
            if not line.strip():
                break
            m = _ATTR.match(line)
            if m and (indent is None or len(m.group(1)) == indent):
                indent, name = len(m.group(1)), m.group(2)
                docs[name] = m.group(3).strip()
            elif name is not None and indent is not None and len(line) - len(line.lstrip()) > indent:
                docs[name] += " " + line.strip()
            else:
                break
    return docs


def _option_type(annotation: Any) -> Any:
    """The annotation as typer takes it: `X | None` as Optional[X], secrets as str."""
    origin = typing.get_origin(annotation)
    if origin in (Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1:
            return Optional[_option_type(args[0])]  # noqa: UP045 (typer reads Optional)
        raise TypeError(f"no option for a union of {args}")
    if getattr(annotation, "__name__", "") == "SecretStr":  # given in clear, kept secret by the settings
        return str
    if origin is Literal or origin is list or annotation in (int, float, str, bool) or _is_path(annotation):
        return annotation
    raise TypeError(f"no option for a field of type {annotation!r}")


def _is_path(annotation: Any) -> bool:
    from pathlib import Path

    return annotation is Path


def _decls(field: str, annotation: Any, names: Mapping[str, tuple[str, ...]]) -> tuple[str, ...]:
    decls = names.get(field) or ("--" + field.replace("_", "-"),)
    if annotation is bool or annotation == Optional[bool]:  # noqa: UP045
        first = decls[0]
        decls = (f"{first}/--no-{first[2:]}", *decls[1:])
    return decls


def dataclass_flags(
    cls: type, skip: Iterable[str] = (), names: Mapping[str, tuple[str, ...]] | None = None
) -> list[Flag]:
    """One flag per field of dataclass `cls` (except `skip`), defaulting to the field's default.

    Args:
        cls: The dataclass.
        skip: Fields that get no flag (filled otherwise).
        names: Option names per field where they are not `--field-name`.
    """
    docs, hints, skip = field_docs(cls), typing.get_type_hints(cls), set(skip)
    flags = []
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        if f.default is dataclasses.MISSING:
            raise TypeError(f"{cls.__name__}.{f.name} has no default: skip it or give it one")
        annotation = _option_type(hints[f.name])
        flags.append(
            Flag(
                f.name,
                _decls(f.name, annotation, names or {}),
                annotation,
                f.default,
                f.default,
                docs.get(f.name, ""),
            )
        )
    return flags


def settings_flags(
    cls: type,
    skip: Iterable[str] = (),
    names: Mapping[str, tuple[str, ...]] | None = None,
    shown: Mapping[str, str] | None = None,
) -> list[Flag]:
    """One flag per field of pydantic-settings `cls` (except `skip`).

    Unset flags stay None so that the environment (`<env_prefix><FIELD>`) applies; the help shows the settings'
    default (or `shown[field]`, for a default computed per process) and the variable.
    """
    docs, skip = field_docs(cls), set(skip)
    prefix = cls.model_config.get("env_prefix", "")
    flags = []
    for name, info in cls.model_fields.items():
        if name in skip:
            continue
        annotation = _option_type(info.annotation)
        if typing.get_origin(annotation) is not list:
            annotation = Optional[annotation]  # noqa: UP045
        default = (shown or {}).get(name) or info.get_default(call_default_factory=True)
        env = f"{prefix}{name}".upper()
        flags.append(
            Flag(
                name,
                _decls(name, annotation, names or {}),
                annotation,
                None,
                default,
                f"{docs.get(name, '')} [{env}]".strip(),
            )
        )
    return flags


def with_flags(*groups: list[Flag]) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Give a command the generated options: `fn(own options..., **flags)` receives them as keywords."""

    def deco(fn: Callable[..., Any]) -> Callable[..., Any]:
        own = [p for p in inspect.signature(fn).parameters.values() if p.kind != p.VAR_KEYWORD]
        extra = [f.parameter() for g in groups for f in g]

        @functools.wraps(fn)
        def command(**kwargs: Any) -> Any:
            return fn(**kwargs)

        command.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
            [p.replace(kind=p.KEYWORD_ONLY) for p in own] + extra
        )
        command.__annotations__ = {
            **typing.get_type_hints(fn),
            **{p.name: p.annotation for p in extra},
        }
        return command

    return deco


def pick(values: Mapping[str, Any], flags: Iterable[Flag]) -> dict[str, Any]:
    """The values of `flags` out of a command's keyword arguments."""
    return {f.field: values[f.field] for f in flags}


def needs(extra: str, what: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Make a command exit with "`what` needs the `extra` extra: pip install ..." when the extra is missing."""

    def deco(fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def command(*args: Any, **kwargs: Any) -> Any:
            try:
                require(extra, what)
            except MissingExtra as e:
                fail(e)
            return fn(*args, **kwargs)

        return command

    return deco


def fail(error: BaseException) -> typing.NoReturn:
    """Print `error: ...` on stderr and exit with status 1."""
    typer.echo(f"error: {error}", err=True)
    raise typer.Exit(1)
