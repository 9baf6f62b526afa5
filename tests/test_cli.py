"""The ``scenesig`` command line: every command module registered, one error handler, bench dispatch."""
import importlib

import pytest

from scenesig import cli
from scenesig.commands.bench import BENCHMARKS


def _subcommands(parser):
    """{name: subparser} of a parser's subcommands."""
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in ("demo", "simulate", "build-map", "map", "localise", "report", "experiment", "bench"):
        assert f"    {name}" in out
    top = _subcommands(cli.build_parser())
    assert set(_subcommands(top["map"])) >= {"show", "verify"}
    assert set(_subcommands(top["experiment"])) == {"matching", "localisation"}
    assert set(_subcommands(top["bench"])) == set(BENCHMARKS)


def test_every_command_module_registers_a_runner():
    parser = cli.build_parser()

    def leaves(p):
        subs = [a for a in p._actions if a.__class__.__name__ == "_SubParsersAction"]
        if not subs:
            yield p
        for a in subs:
            for sp in a.choices.values():
                yield from leaves(sp)

    for leaf in leaves(parser):
        assert callable(leaf.get_default("_run")), leaf.prog
    for name in cli.COMMANDS:
        assert callable(importlib.import_module(f"scenesig.commands.{name}").register)


def test_every_benchmark_module_has_main():
    for module, _ in BENCHMARKS.values():
        assert callable(importlib.import_module(f"scenesig.benchmarks.{module}").main)


def test_data_error_is_exit_2_with_one_message(tmp_path, capsys):
    assert cli.main(["map", "verify", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("scenesig: error: ") and "missing" in err


def test_bench_arguments_reach_the_benchmark(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["bench", "heading", "--help"])
    assert exc.value.code == 0
    assert "scenesig bench heading" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:
        cli.main(["localise", "--bogus"])
    assert exc.value.code == 2
