"""Unknown-key check of a composed Hydra config against its typed schema (issue #32).

OmegaConf refuses ``key=value`` for a key its schema lacks, but Hydra's ``+key=value`` (and a key in a config
group's YAML file) adds it anyway, and ``OmegaConf.to_object`` then drops it without a word: a typo'd
``+training.max_stepz=3`` trained for the default number of steps. :func:`unknown_keys` walks the composed
config and lists every key that is not a field of the dataclass schema, by the dotted name the user typed;
:func:`check_known_keys` turns them into one error that suggests the nearest field.
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from typing import Any

__all__ = ["unknown_keys", "check_known_keys", "unknown_override_keys", "check_override_keys"]


def _dataclass_of(tp: Any) -> type | None:
    """The dataclass inside an annotation (``X``, ``Optional[X]``), or None."""
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(inner) == 1:
            return _dataclass_of(inner[0])
    return None


def unknown_keys(cfg: Any, schema: type, prefix: str = "") -> list[tuple[str, list[str]]]:
    """Keys of ``cfg`` (a DictConfig or nested dict) that are not fields of the dataclass ``schema``.

    Returns:
        ``[(dotted key, [the fields it could have meant])]`` in the config's order; nested dataclass fields
        are checked recursively, fields of other types (dicts, lists, scalars) are leaves.
    """
    from omegaconf import DictConfig, OmegaConf  # lazy, optional dependency: omegaconf

    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=False)
    hints = typing.get_type_hints(schema)
    fields = [f.name for f in dataclasses.fields(schema)]
    out: list[tuple[str, list[str]]] = []
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        if key not in fields:
            out.append((name, [f"{prefix}{m}" for m in difflib.get_close_matches(str(key), fields, n=1)]))
            continue
        sub = _dataclass_of(hints.get(key))
        if sub is not None and isinstance(value, dict):
            out.extend(unknown_keys(value, sub, f"{name}."))
    return out


def unknown_override_keys(argv: list[str], schema: type, groups: tuple[str, ...] = ()
                          ) -> list[tuple[str, list[str]]]:
    """Keys of command-line overrides ``argv`` (``key=value``, ``+key=value``, ``++key=value``, ``~key``) that
    are not fields of ``schema`` — checked before Hydra composes, whose own message for ``key=value`` advises
    ``+key=value``. Flags (``--cfg``), ``hydra.*`` keys, config-group choices (``groups``, ``a/b=…``) and
    ``key@package`` overrides are left to Hydra."""
    out: list[tuple[str, list[str]]] = []
    for arg in argv:
        if arg.startswith("-") or ("=" not in arg and not arg.startswith("~")):
            continue
        key = arg.split("=", 1)[0].lstrip("~+")
        if not key or "/" in key or "@" in key or key.split(".")[0] in ("hydra", *groups):
            continue
        tp: Any = schema
        parts = key.split(".")
        for i, part in enumerate(parts):
            fields = [f.name for f in dataclasses.fields(tp)]
            if part not in fields:
                prefix = ".".join(parts[:i] + [""])
                out.append((key, [f"{prefix}{m}" for m in difflib.get_close_matches(part, fields, n=1)]))
                break
            tp = _dataclass_of(typing.get_type_hints(tp).get(part))
            if tp is None:
                break  # a leaf (or a dict / list field): its value is checked by the schema
    return out


def _raise(bad: list[tuple[str, list[str]]], script: str, error: type[Exception], hint: str | None = None,
           where: str = "") -> None:
    name, near = bad[0]
    more = f" (and {len(bad) - 1} more: {', '.join(b for b, _ in bad[1:])})" if len(bad) > 1 else ""
    mean = f"did you mean {near[0]}? " if near else ""
    hint = f"`python {script} --cfg job` prints every key" if hint is None else hint
    raise error(f"{where}config key {name!r} does not exist{more}; {mean}{hint}")


def check_known_keys(cfg: Any, schema: type, script: str, error: type[Exception], hint: str | None = None,
                     where: str = "") -> None:
    """Raise ``error`` naming the first unknown key of ``cfg`` (see :func:`unknown_keys`) and the fix.

    Args:
        script: how the user runs the app (``train/train.py``), for the ``--cfg job`` hint.
        hint: the command that lists every key, when it is not ``python <script> --cfg job``.
        where: what the message starts with (the file that holds ``cfg``: ``"<path>: "``).
    """
    bad = unknown_keys(cfg, schema)
    if bad:
        _raise(bad, script, error, hint, where)


def check_override_keys(argv: list[str], schema: type, script: str, error: type[Exception],
                        groups: tuple[str, ...] = (), hint: str | None = None, where: str = "") -> None:
    """Raise ``error`` naming the first override key of ``argv`` the schema lacks (see
    :func:`unknown_override_keys`), with the nearest field (``hint`` / ``where``: see :func:`check_known_keys`)."""
    bad = unknown_override_keys(argv, schema, groups)
    if bad:
        _raise(bad, script, error, hint, where)
