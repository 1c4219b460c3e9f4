"""Every Python code block of the user guide (docs/guide/*.rst) runs as written, the blocks
of one page in order in one namespace, as a reader would paste them."""

import pathlib
import re
import textwrap

import pytest

GUIDE = pathlib.Path(__file__).resolve().parents[1] / "docs" / "guide"
BLOCK = re.compile(r"\.\. code-block:: python\n\n((?:(?: {3}.*)?\n)+)")


def _blocks(page: pathlib.Path) -> list[str]:
    return [textwrap.dedent(block) for block in BLOCK.findall(page.read_text())]


@pytest.mark.parametrize("page", sorted(GUIDE.glob("*.rst")), ids=lambda p: p.stem)
def test_guide_code_blocks_run(page):
    blocks = _blocks(page)
    namespace: dict = {}
    for i, code in enumerate(blocks):
        exec(compile(code, f"{page.name}, code block {i + 1}", "exec"), namespace)


def test_the_guide_has_code_blocks():
    """The block pattern finds the guide's examples (a test of the test)."""
    assert sum(len(_blocks(page)) for page in GUIDE.glob("*.rst")) >= 10
