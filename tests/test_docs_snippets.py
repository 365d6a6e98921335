"""Every Python block of the documentation runs as written, as the README's do.

The blocks of a page (``.. code-block:: python``, ``::`` literal blocks that are Python,
and ``>>>`` examples, whose prompts are stripped) run in order in one namespace, as a
reader pasting them into one session would, in a fresh interpreter started in a
temporary folder, with a time limit. Literal blocks that are not Python (shell commands,
printed output) are recognised by not parsing as Python, or by starting with a shell
command.

A block that cannot run as written (it needs a cluster address, or it names a formula
rather than code) is marked by an rST comment on the line before it, ::

    .. not-run: needs a Dask scheduler at that address

    .. code-block:: python

and is skipped; the test lists the marked blocks and checks each reason is given.
"""

import ast
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(path for path in [*DOCS.glob("*.rst"), *DOCS.glob("methods/*.rst")]
               if path.name != "architecture.rst")  # architecture.rst draws the floor plan
MARK = re.compile(r"^\.\. not-run:\s*(?P<reason>.*)$")
SHELL = re.compile(r"^\s*(\$ |python -m |python3 -m |pip |git |cd |export )")


def _indented_block(lines, start):
    """The indented block that starts after line ``start`` (blank lines kept), dedented,
    and the index of the line after it."""
    i = start + 1
    while i < len(lines) and not lines[i].strip():
        i += 1
    body = []
    while i < len(lines) and (not lines[i].strip() or lines[i][:1] in (" ", "\t")):
        body.append(lines[i])
        i += 1
    return textwrap.dedent("\n".join(body)).strip("\n") + "\n", i


def _directive_options_removed(code):
    """Drop a code-block's options (``:caption: ...``) at the top of its body."""
    lines = code.splitlines()
    while lines and re.match(r"^:\w[\w-]*:", lines[0]):
        lines.pop(0)
    return "\n".join(lines).strip("\n") + "\n"


def _from_doctest(code):
    """The code of a ``>>>`` block (prompts stripped, expected output dropped)."""
    out = []
    for line in code.splitlines():
        if line.startswith(">>> ") or line == ">>>":
            out.append(line[4:])
        elif line.startswith("... ") or line == "...":
            out.append(line[4:])
    return "\n".join(out) + "\n"


def _is_python(code):
    if SHELL.match(code):
        return False
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return False
    # a lone name or dotted name (a literal block naming something) is not a snippet
    return not (len(tree.body) == 1 and isinstance(tree.body[0], ast.Expr)
                and isinstance(tree.body[0].value, (ast.Name, ast.Attribute)))


def python_blocks(text):
    """(line, code, reason or None) of every Python block of an rST text, in order."""
    lines = text.splitlines()
    blocks = []
    for i, line in enumerate(lines):
        stripped = line.strip()
        code = None
        if re.match(r"^\.\. code-block::\s*(python|python3|py|pycon)\s*$", stripped):
            code = _directive_options_removed(_indented_block(lines, i)[0])
        elif stripped.endswith("::") and not stripped.startswith(".. "):
            code = _indented_block(lines, i)[0]
            if not code.strip():
                continue
        elif line.startswith(">>>") and (i == 0 or not lines[i - 1].strip()):
            end = i
            while end < len(lines) and lines[end].strip():  # an rST doctest block
                end += 1
            code = "\n".join(lines[i:end]) + "\n"
        else:
            continue
        if code.lstrip().startswith(">>>"):
            code = _from_doctest(code)
        elif not _is_python(code):
            continue
        # the marker: the nearest non-blank line above the block's introduction
        j = i - 1
        while j >= 0 and not lines[j].strip():
            j -= 1
        mark = MARK.match(lines[j].strip()) if j >= 0 else None
        blocks.append((i + 1, code, mark.group("reason").strip() if mark else None))
    return blocks


def test_block_extraction():
    text = textwrap.dedent("""\
        Title
        =====

        Run it::

            python -m pip install .

        Paste this::

            x = 1

        .. code-block:: python

            y = x + 1

        .. not-run: needs a cluster

        .. code-block:: python

            connect("tcp://10.0.0.5:8786")

        Printed::

            Monte Carlo chunk 4 of 5 failed

        >>> z = y * 2
        >>> z
        4
        """)
    assert python_blocks(text) == [(8, "x = 1\n", None), (12, "y = x + 1\n", None),
                                   (18, 'connect("tcp://10.0.0.5:8786")\n', "needs a cluster"),
                                   (26, "z = y * 2\nz\n", None)]


def _page_id(path):
    return path.relative_to(DOCS).as_posix()


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_page_blocks_run_as_written(page, tmp_path):
    blocks = python_blocks(page.read_text(encoding="utf-8"))
    for line, _, reason in blocks:
        assert reason is None or reason, f"{page.name}:{line}: a not-run mark needs a reason"
    runnable = [(line, code) for line, code, reason in blocks if reason is None]
    if not runnable:
        pytest.skip("no runnable Python block")
    # One script per page; each block is compiled with its own file name and line, so a
    # failure names the page and the block.
    # the blocks see the script's own __name__: '__main__' here, '__mp_main__' in the
    # worker processes a local Dask cluster spawns (so the guarded blocks run once)
    script = ["import sys", "namespace = {'__name__': __name__}"]
    for line, code in runnable:
        script.append(f"print('--- block at line {line}', flush=True)")
        script.append(f"exec(compile({code!r}, {f'{page.name}, block at line {line}'!r}, "
                      "'exec'), namespace)")
    (tmp_path / "snippets.py").write_text("\n".join(script) + "\n", encoding="utf-8")
    env = {"MPLBACKEND": "Agg", "PYTHONHASHSEED": "0"}
    import os

    completed = subprocess.run(
        [sys.executable, "snippets.py"], cwd=tmp_path, capture_output=True, text=True,
        timeout=300, env={**os.environ, **env})
    assert completed.returncode == 0, (
        f"{page.name}: a block failed\n{completed.stdout[-2000:]}\n{completed.stderr[-4000:]}")


def test_marked_blocks_are_few_and_listed():
    marked = [(page.name, line, reason) for page in PAGES
              for line, _, reason in python_blocks(page.read_text(encoding="utf-8"))
              if reason is not None]
    total = sum(len(python_blocks(page.read_text(encoding="utf-8"))) for page in PAGES)
    assert total >= 8
    assert len(marked) <= 5, marked
