"""``python -m experiments.study``: a declared study run from a JSON/TOML file gives the rows
of the same study run in-process, resumes a partial run to exactly those rows, and refuses a
folder that holds a study unless told to resume."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import pandas as pd
import pytest

from experiments import study as cli

ROOT = pathlib.Path(cli.__file__).resolve().parent.parent
DECLARATION = {
    "kind": "fir_covariance",
    "grid": {"input": ["white", "prbs"], "N": [60], "sigma": [0.5]},
    "trials": 12,
    "seed": 4,
    "chunk": 4,
}


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "experiments.study", *args],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        check=False,
    )


def table(folder: pathlib.Path) -> pd.DataFrame:
    """The study's rows from its chunk files, in a fixed order, without the timing column."""
    frame = pd.concat(pd.read_parquet(p) for p in sorted(folder.glob("chunks/*.parquet")))
    frame = frame.drop(columns="time").sort_values(["input", "estimator", "trial", "parameter"])
    frame["covariance_row"] = frame["covariance_row"].map(tuple)
    return frame.reset_index(drop=True)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("study_cli")
    path = tmp / "fir.json"
    path.write_text(json.dumps(DECLARATION))
    done = run_cli(str(path), "--out", str(tmp / "out"))
    assert done.returncode == 0, done.stderr
    return tmp, path, done


def test_cli_rows_are_the_in_process_study_rows(cli_run):
    tmp, path, done = cli_run
    assert done.stdout.splitlines()[-1] == f"results: {(tmp / 'out').resolve()}"
    here = cli.declare(cli.read_declaration(path)).run(tmp / "here", progress=False)
    assert len(here.results) == 2 * 12 * 20  # points x trials x taps
    pd.testing.assert_frame_equal(table(tmp / "out" / "study"), table(tmp / "here"))
    assert (tmp / "out" / "report" / "report.md").exists()


def test_resume_after_a_partial_run_gives_the_full_rows(cli_run, tmp_path):
    src, path, _ = cli_run
    full = table(src / "out" / "study")
    out = tmp_path / "out"
    first = run_cli(str(path), "--out", str(out), "--trials", "12")
    assert first.returncode == 0, first.stderr
    chunks = sorted((out / "study" / "chunks").glob("*.parquet"))
    assert len(chunks) == 2 * 3
    for lost in chunks[1::2]:  # a run stopped before these chunks were written
        lost.unlink()
    kept = {p: p.stat().st_mtime_ns for p in chunks[::2]}
    refused = run_cli(str(path), "--out", str(out))
    assert refused.returncode == 2
    assert "already holds results" in refused.stderr and "--resume" in refused.stderr
    resumed = run_cli(str(path), "--out", str(out), "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert {p: p.stat().st_mtime_ns for p in kept} == kept  # finished chunks not recomputed
    pd.testing.assert_frame_equal(table(out / "study"), full)


def test_resume_with_another_declaration_is_refused(cli_run, tmp_path, capsys):
    src, path, _ = cli_run
    other = tmp_path / "other.toml"
    other.write_text(
        'kind = "fir_covariance"\ntrials = 12\nseed = 5\nchunk = 4\n'
        '[grid]\ninput = ["white", "prbs"]\nN = [60]\nsigma = [0.5]\n'
    )
    with pytest.raises(SystemExit) as done:
        cli.main([str(other), "--out", str(src / "out"), "--resume"])
    assert done.value.code == 2
    assert "seed: stored 4, now 5" in capsys.readouterr().err


@pytest.mark.parametrize(
    "text, words",
    [
        ('{"kind": "nonsense"}', "not a known study kind"),
        ('{"kind": "fat_tails", "trails": 3}', "unknown key(s) ['trails']"),
        ('{"kind": "fat_tails", "trials": "12"}', "trials must be an integer, got '12'"),
        ('{"kind": "fat_tails", "grid": [60]}', "grid must be a table"),
        ('{"kind": "fat_tails", "options": "output"}', "options must be a table"),
        ('{"kind": "fat_tails", "options": {"noise": "x"}}', "has no option(s) ['noise']"),
        (
            '{"kind": "consistency", "grid": {"N": [100], "sigma": [0.5], "noise": ["output"]}}',
            "got unknown ['noise'] and missing []",
        ),
        ('{"kind": "fir_covariance", "grid": {"N": [60], "sigma": [0.5]}}', "missing ['input']"),
        (
            '{"kind": "fat_tails", "grid": {"noise": ["cauchy"], "N": [60], "sigma": [0.2]}}',
            "'noise' takes values among",
        ),
        ('{"kind": "fat_tails", "chunk": 0}', "chunk must be an integer >= 1"),
        (
            '{"kind": "fir_covariance", "grid": {"N": ["100"], "sigma": [0.5], '
            '"input": ["white"]}, "trials": 4, "chunk": 2}',
            "N must be an integer >= 1, got '100'",
        ),
    ],
)
def test_bad_declarations_are_named(tmp_path, capsys, text, words):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(SystemExit) as done:
        cli.main([str(path), "--out", str(tmp_path / "out")])
    assert done.value.code == 2
    assert words in capsys.readouterr().err


def test_a_folder_left_by_a_failed_start_takes_the_corrected_declaration(tmp_path):
    """A run that failed before its first chunk leaves DIR/study without results: the
    corrected declaration runs there without --resume."""
    (tmp_path / "out" / "study" / "chunks").mkdir(parents=True)
    (tmp_path / "out" / "study" / "manifest.json").write_text('{"declaration": {}, "hash": ""}')
    path = tmp_path / "fir.JSON"  # the suffix in any case
    path.write_text(
        json.dumps(
            {**DECLARATION, "trials": 4, "grid": {**DECLARATION["grid"], "input": ["white"]}}
        )
    )
    study = cli.main([str(path), "--out", str(tmp_path / "out")])
    assert len(study.results) == 4 * 20
