"""Console and file conventions shared by every experiment (``experiments/_common.py``):
``--quick`` writes to its own folder, ``make_datasets --quick`` leaves ``datasets/`` alone,
the results folder is the last printed line, and ``--help`` states every option's default
without importing the heavy libraries."""

from __future__ import annotations

import argparse
import hashlib
import importlib
import os
import pathlib
import subprocess
import sys

import pytest

from experiments import _common
from experiments._datasets import DATASETS_DIR, load_csv

EXPERIMENTS = sorted(
    p.stem for p in pathlib.Path(_common.__file__).parent.glob("*.py") if not p.stem.startswith("_")
)


def _digests(folder: pathlib.Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.iterdir())
        if p.is_file()
    }


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_quick_folder_is_not_the_full_run_folder(name):
    default_out = DATASETS_DIR if name == "make_datasets" else None
    full = _common.default_output_dir(name, False, default_out)
    quick = _common.default_output_dir(name, True, default_out)
    assert quick != full
    assert quick == _common.DEFAULT_OUT_ROOT / name / "quick"
    assert DATASETS_DIR not in quick.parents


def test_quick_run_writes_its_own_folder_and_prints_it_last(tmp_path, monkeypatch, capsys):
    """A quick run without --out leaves a full run's results alone and ends by printing its
    results folder."""
    from experiments import euler_stability

    monkeypatch.setattr(_common, "DEFAULT_OUT_ROOT", tmp_path)
    full = tmp_path / "euler_stability"
    full.mkdir()
    (full / "euler_stability.csv").write_text("full run\n")
    euler_stability.main(["--quick"])
    lines = capsys.readouterr().out.splitlines()
    quick = full / "quick"
    assert lines[-1] == f"results: {quick.resolve()}"
    assert (quick / "euler_stability.csv").read_text() != "full run\n"
    assert (full / "euler_stability.csv").read_text() == "full run\n"
    assert any(line.startswith("| ") for line in lines)  # the Markdown summary


def test_make_datasets_quick_leaves_datasets_untouched(tmp_path, monkeypatch, capsys):
    from experiments import make_datasets

    monkeypatch.setattr(_common, "DEFAULT_OUT_ROOT", tmp_path)
    before = _digests(DATASETS_DIR)
    make_datasets.main(["--quick", "--only", "vdp_reference", "lorenz_reference"])
    assert _digests(DATASETS_DIR) == before
    quick = tmp_path / "make_datasets" / "quick"
    assert sorted(p.name for p in quick.iterdir()) == [
        "README.md",
        "lorenz_reference.csv",
        "vdp_reference.csv",
    ]
    # the regenerated files are the stored ones (the quick folder is a faithful copy), to the
    # round-off of another CPU that --check allows (the reference trajectory of scipy's DOP853
    # differs in its last bits between an AVX2 and an AVX-512 machine)
    for name in ("vdp_reference", "lorenz_reference"):
        row = make_datasets.compare(name, load_csv(name, quick), load_csv(name))
        assert row["ok"], row
    assert capsys.readouterr().out.splitlines()[-1] == f"results: {quick.resolve()}"


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_help_exits_zero_and_states_every_default(name, monkeypatch, capsys):
    parsers = []
    parse_args = argparse.ArgumentParser.parse_args

    def recording(self, *args, **kwargs):
        parsers.append(self)
        return parse_args(self, *args, **kwargs)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", recording)
    module = importlib.import_module(f"experiments.{name}")
    with pytest.raises(SystemExit) as done:
        module.main(["--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    (parser,) = parsers
    for action in parser._actions:
        if action.option_strings == ["-h", "--help"]:
            continue
        assert action.help, (name, action.option_strings)
        if action.default is not None and action.default is not False:
            shown = " ".join(f"(default: {action.default})".split())
            assert shown in text, (name, action.option_strings, shown)
        elif action.default is None:
            assert "default" in action.help, (name, action.option_strings)
    assert "--quick" in text and f"experiments/out/{name}/quick" in text


HEAVY = ("torch", "numpy", "scipy", "matplotlib", "control")


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_help_imports_no_heavy_library(name):
    """``python -m experiments.<name> --help`` answers before torch, numpy, scipy, matplotlib
    and ``control`` are imported (``-X importtime`` lists every module imported)."""
    root = pathlib.Path(_common.__file__).parent.parent
    done = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", f"experiments.{name}", "--help"],
        cwd=root,
        env={**os.environ, "PYTHONPATH": str(root)},
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert f"python -m experiments.{name}" in done.stdout
    imported = {
        line.rsplit("|", 1)[1].strip()
        for line in done.stderr.splitlines()
        if line.startswith("import time:")
    }
    assert imported, done.stderr  # -X importtime did report
    assert not [m for m in imported if m.split(".")[0] in HEAVY]


def test_make_datasets_names_known_before_imports():
    """``--only`` choices (light constant) are the data sets ``make_datasets`` defines."""
    from experiments import make_datasets

    assert make_datasets.DATASET_NAMES == tuple(make_datasets.BY_NAME)


def test_progress_bar_is_off_when_stderr_is_not_a_terminal(capsys):
    """Under capture (not a TTY) the bar writes nothing and yields every item."""
    assert list(_common.progress(range(5), "items")) == [0, 1, 2, 3, 4]
    assert capsys.readouterr().err == ""
