"""Documentation: the Sphinx site builds cleanly, every public name has a full docstring,
and the code is ruff clean."""

import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest
from numpydoc.validate import validate

import cifilter

ROOT = Path(__file__).resolve().parents[1]

# numpydoc checks every public name must pass: a docstring with a summary, documented
# parameters (and no unknown ones), a Returns section and an Examples section.
REQUIRED_CHECKS = {"GL08", "SS01", "PR01", "PR02", "RT01", "EX01"}


def public_names():
    """(import path, object) of every public function, class and method of the package."""
    found = {}
    modules = [cifilter] + [
        importlib.import_module(info.name)
        for info in pkgutil.walk_packages(cifilter.__path__, prefix="cifilter.")
        if not any(part.startswith("_") for part in info.name.split("."))
    ]
    for module in modules:
        for name in getattr(module, "__all__", []):
            obj = getattr(module, name)
            if not (inspect.isfunction(obj) or inspect.isclass(obj)):
                continue
            path = f"{obj.__module__}.{obj.__qualname__}"
            found[path] = obj
            if inspect.isclass(obj):
                for member_name, member in vars(obj).items():
                    if inspect.isfunction(member) and not member_name.startswith("_"):
                        found[f"{path}.{member_name}"] = member
    return sorted(found)


@pytest.mark.parametrize("path", public_names())
def test_public_docstring_is_complete(path):
    report = validate(path)
    problems = [f"{code}: {message}" for code, message in report["errors"]
                if code in REQUIRED_CHECKS]
    if inspect.isclass(report.get("obj", None)) or path.endswith("FusionResult"):
        problems = [p for p in problems if not p.startswith("RT01")]
    assert not problems, f"{path}:\n" + "\n".join(problems)


def test_sphinx_site_builds_without_warnings(tmp_path):
    # CIFILTER_DOCS_EXECUTE=off: the notebooks are rendered without executing them here,
    # because nbmake executes every one of them in the same test run (docs/conf.py says how
    # the documentation is built with their outputs).
    env = dict(os.environ, CIFILTER_DOCS_EXECUTE="off")
    completed = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "-q",
         str(ROOT / "docs"), str(tmp_path / "html")],
        capture_output=True, text=True, timeout=600, env=env,
    )
    assert completed.returncode == 0, completed.stdout + completed.stderr
    # Every notebook of examples/ is a page of the Tutorials section, without being named.
    notebooks = sorted(path.stem for path in (ROOT / "examples").glob("*.ipynb"))
    assert notebooks
    tutorials = (tmp_path / "html" / "tutorials.html").read_text(encoding="utf-8")
    for name in notebooks:
        assert (tmp_path / "html" / "tutorials" / f"{name}.html").is_file(), name
        assert f'href="tutorials/{name}.html"' in tutorials, name
    check_offline_site(tmp_path / "html")


REMOTE = re.compile(r"""<(?:script|link|img|iframe)\b[^>]*\b(?:src|href)=["'](?:https?:)?//""",
                    re.IGNORECASE)


def check_offline_site(html):
    """The pages work without the network: no page loads a script, style sheet, image or
    frame from another host, and the maths is rendered by a local MathJax copy."""
    pages = sorted(html.rglob("*.html"))
    assert pages
    remote = [f"{page.relative_to(html)}: {match.group(0)}" for page in pages
              for match in REMOTE.finditer(page.read_text(encoding="utf-8"))]
    assert not remote, "remote references:\n" + "\n".join(remote[:20])
    # a page with maths loads MathJax from _static/ and has the maths markup to render
    ci = (html / "methods" / "ci.html").read_text(encoding="utf-8")
    assert re.search(r'<script[^>]*src="\.\./_static/mathjax/tex-chtml\.js', ci)
    assert r"\(" in ci or r"\[" in ci  # MathJax's delimiters around the equations
    mathjax = html / "_static" / "mathjax"
    assert (mathjax / "tex-chtml.js").stat().st_size > 500_000  # the real MathJax bundle
    assert any((mathjax / "output" / "chtml" / "fonts" / "woff-v2").glob("*.woff"))


@pytest.mark.parametrize("page, offending", [
    ('<script src="https://cdn.jsdelivr.net/npm/mathjax@3/es5/tex-mml-chtml.js">', True),
    ("<script defer src='//cdn.example.org/x.js'>", True),
    ('<link rel="stylesheet" href="http://fonts.example.org/a.css">', True),
    ('<script src="_static/mathjax/tex-chtml.js">', False),
    ('<a href="https://stonesoup.readthedocs.io">Stone Soup</a>', False),  # a link to follow
])
def test_remote_reference_pattern(page, offending):
    assert bool(REMOTE.search(page)) is offending


def test_code_is_ruff_clean():
    completed = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", str(ROOT)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )
    assert completed.returncode == 0, completed.stdout + completed.stderr
