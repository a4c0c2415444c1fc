"""Command-line options generated from dataclass configs (mideepbasis.configs)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

import pytest

from mideepbasis.configs import add_config_arguments, config_from_arguments, differences, field_docs, given_fields


@dataclass(frozen=True)
class Inner:
    """A nested config."""

    steps: int = 125
    """Adam steps; 0 turns it off."""

    normals: bool = False
    """Whether the normals move."""


@dataclass(frozen=True)
class Outer:
    """A config with every kind of field."""

    fov: float | None = None
    """Field of view [deg]; None: from EXIF."""

    light: tuple[float, float] | None = field(default=None, metadata={"metavar": "TX,TY"})
    """Known flash offset."""

    names: tuple[str, ...] = ("procedural",)
    """Sources."""

    resolution: int | str = field(default=256, metadata={"parse": lambda text: text if text == "native" else int(text)})
    """Working resolution, or native."""

    refine: Inner = Inner()
    """The inner part."""


def parse(*arguments: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_config_arguments(parser, Outer)
    return parser.parse_args(list(arguments))


def test_field_docstrings_are_read_from_the_source():
    assert field_docs(Outer)["fov"] == "Field of view [deg]; None: from EXIF."
    assert field_docs(Inner)["steps"] == "Adam steps; 0 turns it off."


def test_options_are_named_typed_and_documented_by_their_fields(capsys):
    args = parse("--fov", "30", "--light", "0.1,-0.2", "--names", "a,b", "--resolution", "native",
                 "--refine-steps", "7", "--refine-normals")
    config = config_from_arguments(Outer, args)
    assert config == Outer(fov=30.0, light=(0.1, -0.2), names=("a", "b"), resolution="native",
                           refine=Inner(steps=7, normals=True))
    assert config_from_arguments(Outer, parse("--fov", "none", "--resolution", "64")) == Outer(resolution=64)
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, Outer, skip={"refine.normals"})
    text = " ".join(parser.format_help().split())
    assert "--refine-steps INT Adam steps; 0 turns it off. (default: 125)" in text
    assert "--light TX,TY" in text and "--refine-normals" not in text


def test_only_the_fields_given_replace_the_base():
    base = Outer(fov=50.0, refine=Inner(steps=3, normals=True))
    args = parse("--refine-steps", "9")
    assert given_fields(args, Outer) == {"refine.steps": 9}
    assert config_from_arguments(Outer, args, base) == Outer(fov=50.0, refine=Inner(steps=9, normals=True))
    assert config_from_arguments(Outer, parse(), base) is base
    assert differences(base, Outer()) == [("fov", 50.0, None), ("refine.normals", True, False), ("refine.steps", 3, 125)]
    assert differences(base, Outer(), ignore={"fov", "refine.normals", "refine.steps"}) == []


@pytest.mark.parametrize("arguments, message", [
    (("--light", "0.1"), "2 comma-separated values expected"),
    (("--refine-steps", "many"), "cannot read 'many'"),
    (("--resolution", "big"), "invalid literal"),
])
def test_bad_values_are_one_line_errors_naming_the_option(arguments, message):
    with pytest.raises(argparse.ArgumentError, match=message) as error:
        parse(*arguments)
    assert arguments[0] in str(error.value)


def test_repeated_tuples_join_and_fields_check_their_values():
    from mideepbasis.configs import positive_int

    @dataclass(frozen=True)
    class Checked:
        sources: tuple[str, ...] = ("procedural",)
        """Sources."""

        device: str = field(default="auto", metadata={"choices": ("auto", "cpu")})
        """Where."""

        batch: int = field(default=8, metadata={"parse": positive_int})
        """Materials per step."""

    parser = argparse.ArgumentParser(exit_on_error=False)
    add_config_arguments(parser, Checked)
    args = parser.parse_args(["--sources", "procedural", "--sources", "a,b", "--device", "cpu", "--batch", "2"])
    assert config_from_arguments(Checked, args) == Checked(sources=("procedural", "a", "b"), device="cpu", batch=2)
    assert "--device {auto,cpu}" in parser.format_help()
    for arguments, message in ((["--device", "gpu"], "invalid choice"), (["--batch", "0"], "positive integer")):
        with pytest.raises(argparse.ArgumentError, match=message):
            parser.parse_args(arguments)
