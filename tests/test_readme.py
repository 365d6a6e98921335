"""The README's code runs as written: every ```python block, in order, in one namespace
(as a reader pasting them into one session would), like a doctest of the README."""

import re
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCK = re.compile(r"^```python\n(.*?)^```$", re.MULTILINE | re.DOTALL)


def python_blocks(text):
    """The ```python blocks of a Markdown text, with the line where each starts."""
    return [(text.count("\n", 0, match.start()) + 2, match.group(1))
            for match in BLOCK.finditer(text)]


def test_block_extraction_finds_python_blocks_only():
    text = "x\n```python\na = 1\n```\n```bash\nls\n```\n```python\nb = 2\n```\n"
    assert python_blocks(text) == [(3, "a = 1\n"), (9, "b = 2\n")]


def usage_section(text):
    return text.split("## Usage\n", 1)[1].split("\n## ", 1)[0]


def test_usage_section_has_runnable_python_and_the_docs_line():
    text = README.read_text(encoding="utf-8")
    usage = usage_section(text)
    assert len(python_blocks(usage)) >= 2
    assert "python -m sphinx -b html docs docs/_build/html" in " ".join(usage.split())
    assert "docs/_build/html/index.html" in usage


def test_readme_python_blocks_run_as_written():
    namespace = {"__name__": "readme"}
    blocks = python_blocks(README.read_text(encoding="utf-8"))
    assert blocks
    for line, code in blocks:
        try:
            exec(compile(code, f"README.md, block at line {line}", "exec"), namespace)
        except Exception as exc:  # name the block that failed
            pytest.fail(f"README.md block at line {line} raised {exc!r}")
    # The usage example's claims: kf holds the fusion with filterpy's shapes.
    kf, result = namespace["kf"], namespace["result"]
    assert kf.last_fusion is result and kf.x.shape == (4, 1)
    np.testing.assert_allclose(np.sum(result.weights), 1.0)
