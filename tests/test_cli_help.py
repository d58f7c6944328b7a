"""Every command's `--help`, as a user reads it at 80 columns: positional arguments named in
uppercase (DATASET beside MAP, not `{dataset}`), the demo's help naming every stage it runs,
and the --device defaults (training: auto; evaluate: cpu, saying why)."""

import re

import pytest
import typer
from typer.testing import CliRunner

from slamreloc.cli import app

COMMANDS = sorted(typer.main.get_command(app).commands)


def help_text(*args: str) -> str:
    res = CliRunner().invoke(app, [*args, "--help"], env={"COLUMNS": "80", "NO_COLOR": "1"})
    assert res.exit_code == 0, res.output
    return res.output


def usage_arguments(text: str) -> list[str]:
    """The positional arguments of the usage line (which may wrap): `{MAP} {IMAGE}...` ->
    ['MAP', 'IMAGE']."""
    lines = text.split("Usage:", 1)[1].splitlines()
    end = next((i for i, line in enumerate(lines) if not line.strip()), len(lines))
    usage = " ".join(" ".join(lines[:end]).split())  # rich pads its blank lines with spaces
    return [t.strip("{}.[]") for t in usage.split("[OPTIONS]", 1)[1].split()]


def test_every_command_is_covered():
    assert {"map", "evaluate", "localize", "pseudo-label", "sfm", "export", "demo", "slam",
            "view", "serve"} <= set(COMMANDS)


@pytest.mark.parametrize("command", COMMANDS)
def test_positional_arguments_are_uppercase(command):
    text = help_text(command)
    params = typer.main.get_command(app).commands[command].params
    arguments = [p for p in params if p.param_type_name == "argument"]
    shown = usage_arguments(text)
    assert len(shown) == len(arguments), (command, shown)
    for name in shown:
        assert re.fullmatch(r"[A-Z][A-Z_]*", name), (command, name, text)
    for p in arguments:  # and the Arguments panel lists them by the same names (* required)
        assert p.metavar and p.metavar.strip(".") in shown, (command, p.name)
        star = r"\*\s+" if p.required else r"\s+\[?"
        assert re.search(rf"│ {star}{re.escape(p.metavar)}", text), (command, p.metavar)


def test_known_argument_names():
    assert usage_arguments(help_text("map")) == ["DATASET"]
    assert usage_arguments(help_text("evaluate")) == ["MAP", "DATASET"]
    assert usage_arguments(help_text("localize")) == ["MAP", "IMAGE"]
    assert usage_arguments(help_text("pseudo-label")) == ["MAP", "DATASET"]
    assert usage_arguments(help_text("slam")) == ["DATASET"]
    assert usage_arguments(help_text("sfm")) == ["INPUT"]


def test_demo_help_names_every_stage():
    text = " ".join(help_text("demo").split())
    for stage in ("render the synthetic room", "map: SIFT features", "regressor training",
                  "relocalize the query sequence", "matching baseline", "SLAM backend",
                  "kidnapped twice", "map update from the unlabelled sequence",
                  "result tables", "next commands", "web viewer", "--no-viewer"):
        assert stage in text, stage


def test_device_defaults():
    """Training commands take CUDA when present; evaluate stays on the CPU where localize,
    slam and serve run the regressor (its help says so)."""
    defaults = {}
    for name, command in typer.main.get_command(app).commands.items():
        for p in command.params:
            if p.name == "device":
                defaults[name] = getattr(p.default, "value", p.default)
    assert defaults == {"map": "auto", "pseudo-label": "auto", "evaluate": "cpu"}
    text = " ".join(help_text("evaluate").replace("│", " ").split())  # the panel's lines
    assert "cpu by default, where localize, slam and serve run it" in text


def test_one_option_name_is_one_flag():
    """An option's name (`port`, `scale_from_depth`) is the same flag in every command, so a
    library message naming a setting `name` shows one flag (`slamreloc.cli.with_flags`)."""
    from slamreloc.cli import _flags, with_flags

    root = typer.main.get_command(app)
    seen: dict[str, dict[str, str]] = {}  # name -> flag -> the first command that has it
    for command_name, command in [("slamreloc", root), *sorted(root.commands.items())]:
        for p in command.params:
            if p.param_type_name != "option":
                continue
            flags = [o for o in p.opts if o.startswith("--")]
            assert len(flags) == 1, (command_name, p.name, p.opts)
            seen.setdefault(p.name, {}).setdefault(flags[0], command_name)
    clashes = {name: flags for name, flags in seen.items() if len(flags) > 1}
    assert not clashes, f"one option name, several flags: {clashes}"
    program = {p.name for p in root.params}  # the program's own options precede the command
    assert _flags() == {name: ("slamreloc " if name in program else "") + next(iter(flags))
                        for name, flags in seen.items()}
    assert {"port", "scale", "scale_from_depth", "limit", "topic"} <= set(seen)
    assert with_flags("`topic` pose=NAME") == "slamreloc --topic pose=NAME"
    # a name that is no option stays as written
    assert with_flags("`scale` and `scale_from_depth`: give one; `max_image_size` 2") == \
        "--scale and --scale-from-depth: give one; `max_image_size` 2"
