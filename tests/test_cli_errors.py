"""Every command, given a broken command line (missing or wrong-kind paths, bad numbers, unknown
choices, an unfinished run folder), stops with one clean line on stderr and a non-zero exit
code, never a traceback; commands that read a run refuse one that did not finish."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from gear.cli import build_parser, main
from gear.run_folder import COMPLETE
from gear.synth import generate
from twin_outdir import make_out_dir


@pytest.fixture(scope="module")
def paths(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli")
    unfinished = root / "unfinished"  # what an interrupted `gear train` leaves: no marker
    unfinished.mkdir()
    (unfinished / "config.json").write_text("{}\n")
    (unfinished / "checkpoints").mkdir()
    a_file = root / "a_file.txt"
    a_file.write_text("not a folder\n")
    not_a_run = root / "not_a_run"
    not_a_run.mkdir()
    return {
        "missing": root / "does_not_exist",
        "file": a_file,
        "unfinished": unfinished,
        "not_a_run": not_a_run,
        "finished": make_out_dir(root / "finished"),
        "scene": generate("fridge", root / "scene", res=16, views=4, test_views=1),
        "new": root / "new_folder",
    }


# (command line with {placeholders} for the paths above, text the error line must hold)
CASES = [
    ("info --bogus", "unrecognized arguments"),
    ("synth", "give exactly one of OBJECT"),
    ("synth no_such_object --out {new}", "no_such_object"),
    ("synth fridge --out {new} --res abc", "invalid int value"),
    ("synth fridge --out {new} --res 0", "--res"),
    ("synth fridge --out {new} --views -3", "--views"),
    ("synth fridge --out {new} --effects no_such_effect", "no_such_effect"),
    ("synth --urdf {missing} --out {new}", "does_not_exist"),
    ("synth fridge --out {file} --res 16 --views 2 --test-views 1", "a_file.txt"),
    ("check {missing}", "does_not_exist"),
    ("check {file}", "a_file.txt"),
    ("train {missing} --out {new}", "does_not_exist"),
    ("train {file} --out {new}", "a_file.txt"),
    ("train {scene}", "--out"),
    ("train {scene} --out {new} --parts abc", "invalid int value"),
    ("train {scene} --out {new} --parts 0", "num_parts"),
    ("train {scene} --out {new} --profile no_such_profile", "invalid choice"),
    ("train {scene} --out {new} --schedule no_such_schedule", "invalid choice"),
    ("train {scene} --out {new} --config {missing}", "does_not_exist"),
    ("train {scene} --out {file}", "is a file"),
    ("train {scene} --out {unfinished}", "unfinished run"),
    ("eval {missing} {scene}", "no such output folder"),
    ("eval {file} {scene}", "is a file"),
    ("eval {unfinished} {scene}", "did not finish"),
    ("eval {not_a_run} {scene}", "not the output folder"),
    ("eval {finished} {missing}", "does_not_exist"),
    ("eval {finished} {scene} --samples abc", "invalid int value"),
    ("eval {finished} {scene} --samples 0", "--samples"),
    ("eval {finished} {scene} --background pink", "invalid choice"),
    ("render {missing}", "no such output folder"),
    ("render {file}", "is a file"),
    ("render {unfinished}", "did not finish"),
    ("render {finished} --res abc", "invalid int value"),
    ("render {finished} --t 2", "--t"),
    ("render {finished} --up w", "invalid choice"),
    ("render {finished} --video {new}/clip.avi", "--video"),
    ("view {missing}", "no such output folder"),
    ("view {file}", "is a file"),
    ("view {unfinished}", "did not finish"),
    ("view {finished} --port 70000", "--port"),
    ("view {finished} --up w", "invalid choice"),
    ("export {missing} --urdf {new}", "no such output folder"),
    ("export {file} --urdf {new}", "is a file"),
    ("export {unfinished} --urdf {new}", "did not finish"),
    ("export {finished} --urdf {new} --faces abc", "invalid int value"),
    ("export {finished} --urdf {new} --faces 0", "--faces"),
    ("export {finished} --urdf {new} --density 1 --mass 2", "not allowed with"),
    ("export {finished} --urdf {file}", "a_file.txt"),
    ("batch {scene}", "--out"),
    ("batch {missing} --out {new}", "does_not_exist"),
    ("batch {scene} --out {file}", "is a file"),
    ("batch {scene} --out {new} --profile no_such_profile", "invalid choice"),
    ("batch {scene} --out {new} --config {missing}", "does_not_exist"),
    ("batch {scene} --out {new} --cpus-per-run 0", "--cpus-per-run"),
    ("batch {scene} --out {new} --memory-per-run 0", "--memory-per-run"),
    ("batch {scene} --out {new} --retries -1", "--retries"),
    ("batch {scene} --out {new} --faces 0", "--faces"),
    ("bench", "required"),
    ("bench no_such_target", "invalid choice"),
    ("bench geometry --only no_such_family", "invalid choice"),
    ("bench raster --repeats abc", "invalid int value"),
    ("bench raster --cases no_such_case", "--cases"),
    ("bench step {new}", "--scene"),
    ("bench step {new} --scene {scene} --steps 0", "--steps"),
    ("bench step {missing} --scene {scene}", "past stage 2"),
]


def run_main(argv: list[str], capsys) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as stop:  # argparse's exit on a bad command line
        code = stop.code if isinstance(stop.code, int) else 1
    captured = capsys.readouterr()
    return code, captured.err


def _commands() -> set[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return set(sub.choices)


def test_the_walk_covers_every_command():
    walked = {line.split()[0] for line, _ in CASES}
    assert walked == _commands()


@pytest.mark.parametrize(("line", "expected"), CASES, ids=[c[0] for c in CASES])
def test_broken_arguments_give_one_clean_line_and_a_nonzero_exit(paths, capsys, line, expected):
    argv = [word.format(**{k: str(v) for k, v in paths.items()}) for word in line.split()]
    code, err = run_main(argv, capsys)
    assert code != 0
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("gear") and "error: " in lines[0]
    assert expected in lines[0]


@pytest.mark.parametrize("command", ["eval", "render", "view", "export"])
def test_commands_reading_a_run_refuse_an_unfinished_one_naming_the_fix(paths, capsys, command):
    extra = {"eval": [str(paths["scene"])], "export": ["--urdf", str(paths["new"])]}
    code, err = run_main([command, str(paths["unfinished"]), *extra.get(command, [])], capsys)
    assert code == 1
    assert f"its run did not finish (no {COMPLETE})" in err and "--resume" in err
    assert not (paths["unfinished"] / "twin_renders").exists()  # nothing written beside it


def test_a_broken_command_line_from_the_shell_is_one_line_without_traceback(paths):
    result = subprocess.run(
        [sys.executable, "-m", "gear", "render", str(paths["unfinished"])],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 1
    assert result.stderr.strip().count("\n") == 0 and "Traceback" not in result.stderr
    assert "did not finish" in result.stderr
