"""Command lines from typed configs (``tbsim_env.core.config_cli``): one source for options
and help."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import pytest

from tbsim_env.cli.app import build_parser
from tbsim_env.cli.commands import COMMANDS
from tbsim_env.core.config_cli import attribute_help, config_parser, option, parse_config


@dataclass(frozen=True, kw_only=True)
class Base:
    """Shared options.

    Attributes:
        seed: seed of everything.
    """

    seed: int = 0


@dataclass(frozen=True, kw_only=True)
class Toy(Base):
    """A toy command.

    Attributes:
        files: input files, one or more.
        out: where to write, 100% of it.
        rate: a rate in 1/s, split over
            two lines.
        mode: how.
        quiet: say less.
        limit: optional cap.
        ray: cluster address, or a local instance without one.
    """

    files: tuple[str, ...] = field(metadata=option(positional=True))
    out: str
    rate: float = 0.5
    mode: str = field(default="a", metadata=option(choices=lambda: ("a", "b")))
    quiet: bool = False
    limit: int | None = None
    ray: str | None = field(default=None, metadata=option(nargs="?", const="local"))


def test_fields_become_typed_options():
    p = config_parser(Toy)
    cfg = parse_config(Toy, p.parse_args(["x", "y", "--out", "o", "--rate", "2", "--mode", "b"]))
    assert cfg == Toy(files=("x", "y"), out="o", rate=2.0, mode="b")
    cfg = parse_config(Toy, p.parse_args(["x", "--out", "o", "--quiet", "--limit", "3", "--ray"]))
    assert cfg.quiet and cfg.limit == 3 and cfg.ray == "local" and cfg.seed == 0
    with pytest.raises(SystemExit):
        p.parse_args(["x"])  # --out is required
    with pytest.raises(SystemExit):
        p.parse_args(["x", "--out", "o", "--mode", "c"])


def test_help_comes_from_the_docstrings_of_the_class_and_its_bases(capsys):
    with pytest.raises(SystemExit):
        config_parser(Toy).parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "a rate in 1/s, split over two lines. (default: 0.5)" in text
    assert "seed of everything. (default: 0)" in text
    assert "where to write, 100% of it." in text
    assert attribute_help(Toy)["rate"] == "a rate in 1/s, split over two lines."


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_tbsim_option_is_documented(name):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices[name]
    helps = {a.dest: a.help for a in sub._actions if a.dest != "help"}
    fields = {f.name for f in dataclasses.fields(COMMANDS[name])}
    assert set(helps) == fields
    assert all(len(h.split(" (default")[0]) > 5 for h in helps.values()), helps


def test_view_refuses_a_submission_and_a_policy(capsys):
    from tbsim_env.cli import main

    code = main(["view", "x.tfrecord", "--submission", "s", "--policy", "log_replay", "--out", "v"])
    assert code == 2 and "not both" in capsys.readouterr().err
