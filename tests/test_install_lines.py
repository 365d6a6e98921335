"""Every install line of the repository names the right distribution.

The import name is ``cifilter``, but ``cifilter`` on PyPI is an unrelated project (0.4.2,
2013, which fails to build), so ``pip install cifilter[stonesoup]`` installs something
else. The distribution is named in setup.cfg; every ``pip install`` line of the README, the
docs, the notebooks, the error messages and the command line's help must install either
the working copy (``pip install .``, ``".[stonesoup]"``, ``-e ".[test]"``) or that name, and
no text may name an extra of the wrong distribution (``cifilter[fast]``).
"""

import configparser
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

def distribution_name():
    config = configparser.ConfigParser(interpolation=None)
    config.read(ROOT / "setup.cfg", encoding="utf-8")
    return config["metadata"]["name"]


def text_files():
    """The files a user reads install lines in (generated copies excluded)."""
    patterns = ["README.md", "CONTRIBUTING.md", "setup.cfg", "pyproject.toml", ".ci/run",
                "docs/**/*.rst", "docs/conf.py", "examples/*.ipynb", "examples/*.md",
                "cifilter/**/*.py", "benchmarks/**/*.py", "tests/**/*.py"]
    found = set()
    for pattern in patterns:
        found.update(path for path in ROOT.glob(pattern) if path.is_file())
    generated = ROOT / "docs" / "tutorials"
    this = Path(__file__).resolve()
    return sorted(path for path in found
                  if generated not in path.parents and path.resolve() != this)


# "pip install" and what follows on the line, up to the end of a code span or sentence.
PIP_INSTALL = re.compile(r"pip3?\s+install\s+(?P<args>[^`\n]*)")
# A requirement naming the distribution "cifilter", with or without quotes, extras or a
# version ("cifilter", 'cifilter[fast]', "cifilter>=0.1"); cifilter-fusion is another name.
WRONG_REQUIREMENT = re.compile(r"""["'\\]*cifilter(\[[^\]]*\])?([<>=!~].*)?["'\\]*""")


def first_requirement(args):
    """What a pip install line installs first: the first word after the options (``-e``
    takes the requirement as its value; the other options used here take none)."""
    for word in args.split():
        if word in ("&&", ";", "|") or word.startswith("#"):
            break
        if word.startswith("-"):
            continue
        return word
    return ""
# An extra of the wrong distribution anywhere in the text: cifilter[stonesoup].
WRONG_EXTRA = re.compile(r"(?<![\w./-])cifilter\[")


def problems_in(text, name):
    """The offending lines of a text: (line number, line)."""
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        bad = bool(WRONG_EXTRA.search(line))
        for match in PIP_INSTALL.finditer(line):
            requirement = first_requirement(match.group("args"))
            bad = bad or bool(WRONG_REQUIREMENT.fullmatch(requirement))
        if bad:
            found.append((number, line.strip()))
    return found


@pytest.mark.parametrize("line", [
    "pip install cifilter[stonesoup]",
    "    pip install cifilter",
    "`pip install cifilter[fast]` installs numba",
    '"pip install cifilter[distributed]"',
    "pip install 'cifilter>=0.1'",
    "the optional extras cifilter[plot] and",
])
def test_wrong_lines_are_found(line):
    assert problems_in(line, "cifilter-fusion") == [(1, line.strip())]


@pytest.mark.parametrize("line", [
    'python -m pip install ".[stonesoup]"',
    'python -m pip install -e ".[test]" && python -m pytest',
    "python -m pip install . && python -m cifilter demo",
    'pip install "cifilter-fusion[stonesoup]"',
    "pip install cifilter-fusion",
    "import cifilter.stonesoup; pip install stonesoup",
    "from cifilter import fuse",
    "git clone https://example.org/cifilter && cd cifilter && pip install .",
])
def test_right_lines_pass(line):
    assert problems_in(line, "cifilter-fusion") == []


def test_the_distribution_has_its_own_name():
    # "cifilter" on PyPI is an unrelated project; the import name stays cifilter.
    name = distribution_name()
    assert name != "cifilter"
    assert name == "cifilter-fusion"


def test_every_install_line_names_the_right_distribution():
    name = distribution_name()
    offending, named = [], 0
    for path in text_files():
        relative = path.relative_to(ROOT).as_posix()
        text = path.read_text(encoding="utf-8")
        named += text.count(f"{name}[")
        offending += [f"{relative}:{number}: {line}" for number, line in problems_in(text, name)]
    assert not offending, "install lines naming the wrong distribution:\n" + "\n".join(offending)
    assert named > 0  # the published name is given somewhere (README, docs, messages)
