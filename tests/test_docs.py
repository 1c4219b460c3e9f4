"""The documentation tree (docs/) is consistent: every public name is in the API reference,
every page is in a toctree, and (where Sphinx is installed) the strict build passes."""

import importlib.util
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

import integrators
import sysid

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _documented_modules() -> set[str]:
    text = "".join(p.read_text(encoding="utf-8") for p in (DOCS / "api").glob("*.rst"))
    return set(re.findall(r"^\.\. automodule:: (\S+)", text, flags=re.M))


@pytest.mark.parametrize("package", [integrators, sysid, sysid.zoo], ids=lambda p: p.__name__)
def test_every_public_name_is_in_an_automodule_of_the_api_reference(package):
    modules = _documented_modules()
    missing = []
    for name in package.__all__:
        obj = getattr(package, name)
        if isinstance(obj, types.ModuleType):  # a module or a subpackage (sysid.zoo)
            home = obj.__name__
            if home in modules or any(m.startswith(home + ".") for m in modules):
                continue
        elif hasattr(obj, "__module__"):
            home = obj.__module__
        else:  # a constant such as TABLEAU_NAMES: documented with the module defining it
            home = next((m for m in modules if hasattr(importlib.import_module(m), name)), None)
        if home not in modules:
            missing.append(f"{name} ({home})")
    assert not missing, f"public names without an automodule in docs/api: {missing}"


def test_api_reference_documents_no_private_module():
    private = [m for m in _documented_modules() if any(p.startswith("_") for p in m.split("."))]
    assert not private


def test_every_page_is_in_a_toctree():
    pages = {
        p.relative_to(DOCS).with_suffix("").as_posix()
        for p in DOCS.rglob("*")
        if p.suffix in (".rst", ".md") and not p.relative_to(DOCS).parts[0].startswith("_")
    }
    listed = {"index"}
    for page in pages:
        text = (DOCS / page).with_suffix(".rst")
        if not text.exists():
            continue
        for block in re.findall(r"\.\. toctree::\n((?:   .*\n|\n)+)", text.read_text("utf-8")):
            entries = [e.strip() for e in block.splitlines() if e.strip() and ":" not in e]
            base = Path(page).parent
            listed |= {(base / e).as_posix() for e in entries}
    assert pages == listed, f"not in a toctree: {pages - listed}; missing: {listed - pages}"


def test_readme_links_to_the_benchmarks_page():
    readme = (DOCS.parent / "README.md").read_text(encoding="utf-8")
    for link in re.findall(r"\]\((docs/[^)]+)\)", readme):
        assert (DOCS.parent / link).exists(), link


@pytest.mark.skipif(
    importlib.util.find_spec("sphinx") is None or importlib.util.find_spec("myst_parser") is None,
    reason="sphinx / myst-parser not installed (pip install -e '.[docs]')",
)
def test_docs_build_strictly(tmp_path):
    cmd = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-E", "-b", "html"]
    run = subprocess.run(
        [*cmd, "-d", str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr[-4000:]
    assert (tmp_path / "html" / "notes.html").exists()
