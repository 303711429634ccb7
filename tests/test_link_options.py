"""`ServeOptions` / `ProvisionOptions`: what a user chooses is validated where it is built,
from one table of constraints, as one line naming the option, its value and what is allowed;
the command line says the same line with its flag (exit code 1, as every user error)."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from host.cli import main as cli_main
from host.link import provision, serve
from host.link.options import (
    PROVISION_CONSTRAINTS,
    SERVE_CONSTRAINTS,
    OptionError,
    ProvisionOptions,
    ServeOptions,
)


@pytest.mark.parametrize("cls, table", [(ServeOptions, SERVE_CONSTRAINTS),
                                        (ProvisionOptions, PROVISION_CONSTRAINTS)])
def test_every_option_has_one_constraint_and_its_default_passes(cls, table):
    assert set(table) == {f.name for f in dataclasses.fields(cls)}
    cls()  # the defaults are allowed
    with pytest.raises(dataclasses.FrozenInstanceError):
        cls().baud = 9600


@pytest.mark.parametrize("function", [serve, provision])
def test_serve_and_provision_take_at_most_eight_parameters(function):
    assert len(inspect.signature(function).parameters) <= 8


@pytest.mark.parametrize("cls, option, value, allowed", [
    (ServeOptions, "fps", -1.0, "a number >= 0"),
    (ServeOptions, "scores", "magic", "one of auto, motion, interpolate"),
    (ServeOptions, "deadline_s", 0.0, "a number of seconds > 0"),
    (ServeOptions, "rest", 1.5, "'exact', 'correction' or an object SSIM in (0, 1)"),
    (ServeOptions, "max_frames", 0, "an integer >= 1 or None"),
    (ServeOptions, "baud", 9600.5, "an integer > 0"),
    (ServeOptions, "reconnect", "yes", "True or False"),
    (ProvisionOptions, "chunk_bytes", 0, "an integer >= 1 or None"),
    (ProvisionOptions, "retransmit", "fast", "one of selective, go-back-n"),
    (ProvisionOptions, "request_timeout_s", float("nan"), "a number > 0"),
])
def test_a_bad_option_is_one_line_naming_it_its_value_and_what_is_allowed(
        cls, option, value, allowed):
    with pytest.raises(OptionError) as err:
        cls(**{option: value})
    line = str(err.value)
    assert line.startswith(f"{option}={value!r}: expected ") and allowed in line
    assert "\n" not in line and isinstance(err.value, ValueError)


@pytest.mark.parametrize("args, line", [
    (["serve", "M.ecs", "--port", "mem://x", "--fps", "-1"],
     "--fps -1.0: expected a number >= 0"),
    (["serve", "M.ecs", "--port", "mem://x", "--deadline", "0"],
     "--deadline 0.0: expected a number of milliseconds > 0"),
    (["serve", "M.ecs", "--port", "mem://x", "--rest-quality", "best"],
     "--rest-quality best: expected 'exact', 'correction' or an object SSIM in (0, 1)"),
    (["serve", "M.ecs", "--port", "mem://x", "--max-frames", "0"],
     "--max-frames 0: expected an integer >= 1"),
    (["provision", "M.ecs", "--port", "mem://x", "--chunk", "0"],
     "--chunk 0: expected an integer >= 1"),
    (["provision", "M.ecs", "--port", "mem://x", "--timeout", "0"],
     "--timeout 0.0: expected a number > 0"),
])
def test_the_command_line_says_the_options_line_with_its_flag(args, line, capsys):
    # the options are checked before the model file is looked for (M.ecs does not exist)
    assert cli_main(args) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(f"eigencast {args[0]}: error: {line}"), err
