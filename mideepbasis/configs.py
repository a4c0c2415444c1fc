"""Command-line options generated from dataclass configs, as nerfstudio does with tyro.

Every field of a config dataclass becomes an option named after it (``refine_steps`` of a nested
``refine: RefineConfig`` becomes ``--refine-steps``), typed from its annotation and documented
by the string literal under it (its attribute docstring), so a new field needs no CLI code:

    add_config_arguments(parser, CaptureConfig, skip={"light"})
    config = config_from_arguments(CaptureConfig, args)

Options default to "not given" (``argparse.SUPPRESS``): ``config_from_arguments`` starts from a
base config (the class's defaults, or a stored one when a run resumes) and replaces only the
fields the user gave, and ``given_fields`` says which those were.

A field may carry ``metadata={"parse": function, "metavar": "...", "choices": (...)}`` for a value
the annotation does not describe (``N|native``, ``positive_int``, a set of names). Tuples are
written comma-separated (``--light 0.1,-0.2``); an option of a variable-length tuple may also be
repeated, its values joined (``--data procedural --data FOLDER``); ``none`` gives None where the
annotation allows it.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap
import types
import typing
from functools import lru_cache

from .errors import InputError

#: The separator of a nested field's path in argparse's namespace.
_SEPARATOR = "__"


@lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """The attribute docstrings of a dataclass's fields (the string literal under each), by name."""
    docs = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body
        for statement, following in zip(body, body[1:]):
            if (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)
                    and isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                    and isinstance(following.value.value, str)):
                docs[statement.target.id] = " ".join(following.value.value.split())
    return docs


def positive_int(text: str) -> int:
    """An integer of at least 1, for a field's ``metadata={"parse": positive_int}``."""
    value = int(text)
    if value < 1:
        raise ValueError(f"must be a positive integer, got {value}")
    return value


def unit_share(text: str | float) -> float:
    """A number in [0, 1], for a field's ``metadata={"parse": unit_share}`` (and its ``__post_init__``)."""
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"must lie in [0, 1], got {value:g}")
    return value


def non_negative(text: str | float) -> float:
    """A number of at least 0, for a field's ``metadata={"parse": non_negative}`` (and its ``__post_init__``)."""
    value = float(text)
    if not value >= 0.0:
        raise ValueError(f"must be 0 or more, got {value:g}")
    return value


class _JoinRepeated(argparse.Action):
    """A variable-length tuple option given more than once: its values joined in order."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, tuple(getattr(namespace, self.dest, ())) + tuple(values))


def _is_variable_tuple(annotation) -> bool:
    annotation = _parts(annotation)[0]
    arguments = typing.get_args(annotation)
    return typing.get_origin(annotation) is tuple and len(arguments) == 2 and arguments[1] is Ellipsis


def _parts(annotation) -> tuple[object, bool]:
    """(the annotation without ``None``, whether None is allowed)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        arguments = [a for a in typing.get_args(annotation) if a is not type(None)]
        optional = len(arguments) < len(typing.get_args(annotation))
        return (arguments[0] if len(arguments) == 1 else typing.Union[tuple(arguments)]), optional
    return annotation, False


def _scalar_parser(annotation):
    if annotation in (int, float, str):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        choices = typing.get_args(annotation)

        def parse_union(text: str):
            for choice in (int, float, str):
                if choice in choices:
                    try:
                        return choice(text)
                    except ValueError:
                        continue
            raise ValueError(text)

        return parse_union
    raise TypeError(f"no command-line parser for {annotation!r}: give the field metadata={{'parse': ...}}")


def _nested(annotation) -> type | None:
    """The dataclass a field holds (alone, or in a union such as ``NetworkConfig | dict | None``)."""
    if dataclasses.is_dataclass(annotation):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return next((a for a in typing.get_args(annotation) if dataclasses.is_dataclass(a)), None)
    return None


def _value_parser(annotation):
    """A function from the option's text to the field's value."""
    annotation, optional = _parts(annotation)
    if typing.get_origin(annotation) is tuple:
        arguments = typing.get_args(annotation)
        variable = len(arguments) == 2 and arguments[1] is Ellipsis
        items = [_scalar_parser(arguments[0])] if variable else [_scalar_parser(a) for a in arguments]

        def parse_tuple(text: str):
            parts = [p.strip() for p in text.split(",") if p.strip()]
            if not variable and len(parts) != len(items):
                raise ValueError(f"{len(items)} comma-separated values expected")
            return tuple((items[0] if variable else items[i])(p) for i, p in enumerate(parts))

        parse = parse_tuple
    else:
        parse = _scalar_parser(annotation)

    def parse_value(text: str):
        if optional and text.strip().lower() == "none":
            return None
        try:
            return parse(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(f"cannot read {text!r} ({error})") from None

    return parse_value


def _option(path: tuple[str, ...]) -> str:
    """The option of a field path: ``("refine", "steps")`` is ``--refine-steps``."""
    return "--" + "-".join(path).replace("_", "-")


def _destination(path: tuple[str, ...]) -> str:
    """The namespace attribute of a field path: ``refine__steps``."""
    return _SEPARATOR.join(path)


def add_config_arguments(parser: argparse.ArgumentParser, cls: type, skip: set[str] | frozenset[str] = frozenset(),
                         defaults=None, _path: tuple[str, ...] = (), describe: bool = True,
                         shown: set[str] | frozenset[str] | None = None, _hidden: dict | None = None) -> None:
    """One option per field of the dataclass ``cls`` (nested dataclasses recursively, their options
    prefixed with the field's name). ``skip`` names fields (dotted for nested ones: ``refine.lr``)
    the command sets otherwise; ``defaults`` (an instance) is shown in the help (default: the class's).
    ``describe``: the help of each option is its field's docstring, which is read from the source
    (60 - 100 ms a command); False where no help will be printed leaves it out.

    ``shown``: the fields (dotted) whose help a brief ``--help`` prints, each in its docstring's
    first sentence; the others are advanced: their options work as ever but appear only by name,
    listed under a heading per group (``advanced_groups``), and in full with ``--help-all``.
    None: every option in full."""
    defaults = defaults if defaults is not None else cls()
    hints, docs = typing.get_type_hints(cls), (field_docs(cls) if describe else {})
    top = _hidden is None
    hidden: dict[str, list[str]] = {} if top else _hidden
    for item in dataclasses.fields(cls):
        path = _path + (item.name,)
        dotted = ".".join(path)
        if dotted in skip:
            continue
        annotation = hints[item.name]
        default = getattr(defaults, item.name)
        if _nested(annotation):
            add_config_arguments(parser, _nested(annotation), skip, default, path, describe, shown, hidden)
            continue
        option = _option(path)
        documentation = docs.get(item.name, "").replace("``", "")
        if shown is not None:
            documentation = first_sentence(documentation)
        help_text = f"{documentation} (default: {_show(default)})".replace("%", "%%")
        if shown is not None and dotted not in shown:
            hidden.setdefault(path[0] if len(path) > 1 else "", []).append(option)
            help_text = argparse.SUPPRESS
        if _parts(annotation)[0] is bool:
            parser.add_argument(option, dest=_destination(path), action=argparse.BooleanOptionalAction,
                                default=argparse.SUPPRESS, help=help_text)
            continue
        parse = _checked(item.metadata["parse"]) if "parse" in item.metadata else _value_parser(annotation)
        extra = {"choices": item.metadata["choices"]} if "choices" in item.metadata else {}
        metavar = item.metadata.get("metavar") or ("{" + ",".join(extra["choices"]) + "}" if extra else _metavar(annotation))
        if _is_variable_tuple(annotation):
            extra["action"] = _JoinRepeated
        parser.add_argument(option, dest=_destination(path), type=parse, default=argparse.SUPPRESS,
                            metavar=metavar, help=help_text, **extra)
    if top and hidden and describe:
        for group, options in hidden.items():
            title = f"advanced{' ' + group if group else ''} options (mideepbasis {parser.prog.split()[-1]} --help-all " \
                    "explains each)"
            parser.add_argument_group(title, "  ".join(options))


def first_sentence(text: str) -> str:
    """A docstring's first sentence (up to its first full stop followed by a space, an "e.g." or
    "i.e." not counting), markup removed."""
    import re

    text = text.replace("``", "")
    end = re.search(r"(?<!e\.g)(?<!i\.e)\.\s", text)
    return text if end is None else text[:end.start() + 1]


def _checked(parse):
    """A field's own parser, its ValueError turned into argparse's one-line error."""
    def parse_checked(text: str):
        try:
            return parse(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    return parse_checked


def _metavar(annotation) -> str:
    annotation, optional = _parts(annotation)
    if typing.get_origin(annotation) is tuple:
        arguments = typing.get_args(annotation)
        text = "A,B,..." if len(arguments) == 2 and arguments[1] is Ellipsis else ",".join("ABCDEFGH"[:len(arguments)])
    else:
        text = getattr(annotation, "__name__", "VALUE").upper()
    return text + ("|none" if optional else "")


def _show(value) -> str:
    if isinstance(value, tuple):
        return ",".join(str(v) for v in value) or "()"
    return str(value)


def given_fields(args: argparse.Namespace, cls: type) -> dict[str, object]:
    """The fields of ``cls`` the user gave on the command line, by dotted path (``refine.steps``)."""
    given = {}

    def visit(klass: type, path: tuple[str, ...]) -> None:
        hints = typing.get_type_hints(klass)
        for item in dataclasses.fields(klass):
            here = path + (item.name,)
            if _nested(hints[item.name]):
                visit(_nested(hints[item.name]), here)
            elif hasattr(args, _destination(here)):
                given[".".join(here)] = getattr(args, _destination(here))

    visit(cls, ())
    return given


def config_from_arguments(cls: type, args: argparse.Namespace, base=None):
    """``base`` (default: ``cls()``) with the fields given on the command line replaced.

    A combination the config refuses (its own check across fields, ``__post_init__``; each option's
    own value argparse checks) raises ``InputError``, its message led by the command's name
    (``args.command``) where there is one: the command line prints it as one line."""
    try:
        return _with_arguments(cls, args, base, ())
    except (ValueError, TypeError) as error:
        command = getattr(args, "command", None)
        raise InputError(f"{command}: {error}" if command else str(error)) from None


def _with_arguments(cls: type, args: argparse.Namespace, base, _path: tuple[str, ...]):
    """``config_from_arguments`` of the fields under ``_path``, errors as the configs raise them."""
    config = base if base is not None else cls()
    hints = typing.get_type_hints(cls)
    changes = {}
    for item in dataclasses.fields(cls):
        path = _path + (item.name,)
        if _nested(hints[item.name]):
            nested = _with_arguments(_nested(hints[item.name]), args, getattr(config, item.name), path)
            if nested is not getattr(config, item.name):
                changes[item.name] = nested
        elif hasattr(args, _destination(path)):
            changes[item.name] = getattr(args, _destination(path))
    return dataclasses.replace(config, **changes) if changes else config


def flatten(config, prefix: str = "") -> dict[str, object]:
    """A config's fields by dotted path, nested configs (and dicts of them) flattened."""
    values = dataclasses.asdict(config) if dataclasses.is_dataclass(config) else config
    flat = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = list(value) if isinstance(value, tuple) else value
    return flat


def differences(stored, current, ignore: set[str] | frozenset[str] = frozenset()) -> list[tuple[str, object, object]]:
    """(dotted field, stored value, current value) for every field of two configs that differs."""
    a, b = flatten(stored), flatten(current)
    return [(key, a.get(key), b.get(key)) for key in sorted(set(a) | set(b))
            if key not in ignore and a.get(key) != b.get(key)]


#: Settings a stored config may hold that this version lacks, by config, each with the value that
#: turns it off. A stored config (a checkpoint's network, a run's settings) that holds one at that
#: value reads as if it did not; another value is refused (``drop_removed_fields``).
REMOVED_FIELDS: dict[str, dict[str, object]] = {
    # A second normal unit beside the first; the albedo shading as the normal unit's eighth input.
    "NetworkConfig": {"normal_booster_width": 0, "normal_unit_albedo": False},
    # The normal pool's mean of the crops' RMSE (its mean squared error stays).
    "TrainConfig": {"normal_pool_loss": "mse"},
    # The procedural relief turned inside out, and scaled down to a low tilt.
    "GeneratorConfig": {"relief_inversion_probability": 0.0, "low_relief_probability": 0.0,
                        "low_relief_tilt_deg": (0.3, 2.4)},
}


def drop_removed_fields(kind: str, values: dict, source: str, error: type[Exception] = ValueError) -> dict:
    """A copy of a stored ``kind`` config's fields (``NetworkConfig``, ...) without those this
    version lacks (``REMOVED_FIELDS``), each of which must hold its off value (a list
    stored for a tuple counts as the tuple); another value raises ``error`` in one line that names
    the field and ``source`` (the file)."""
    kept = dict(values)
    for name, off in REMOVED_FIELDS.get(kind, {}).items():
        if name not in kept:
            continue
        value = kept.pop(name)
        if (tuple(value) if isinstance(value, list) else value) != off:
            raise error(f"{source}: uses {name} = {value!r}, a setting this version does not have "
                        f"(it reads only {off!r}, the setting's off value)")
    return kept
