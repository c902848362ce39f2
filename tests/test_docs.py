"""The documentation tells the truth about the code and the data:

- the benchmarks page and the README's results table are what ``bench/pages.py`` makes of the
  committed ``bench/results/*.json`` (a JSON changed without regenerating the pages fails here);
- every ``python`` block of the README and of the documentation pages runs, page by page, the
  blocks of a page in order in one fresh process (so a later block sees an earlier one's names);
  a block preceded by ``<!-- test: skip ... -->`` (an excerpt of a file tested elsewhere) is not
  run, and one preceded by ``<!-- test: slow -->`` only with ``TWINRL_DOCS_SLOW=1``;
- every ``twinrl ...`` line of a shell block parses with the real command-line parser, so no page
  shows a command or a flag that does not exist;
- the README stays under 200 lines; the site builds with ``mkdocs build --strict`` where MkDocs is
  installed (``pip install -e '.[docs]'``; ``make docs`` does it).
"""

import os
import re
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
MARK = re.compile(r"<!--\s*test:\s*(\w+)[^>]*-->\s*$")
SLOW = os.environ.get("TWINRL_DOCS_SLOW") == "1"


def blocks(page: Path, lang: set[str]):
    """(line, marker, code) of each fenced block of ``page`` in ``lang``; ``marker`` is the
    ``<!-- test: X -->`` word on the line before the fence, if any."""
    text = page.read_text()
    for m in FENCE.finditer(text):
        if m.group(1) not in lang:
            continue
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        mark = MARK.search(before)
        yield text[:m.start()].count("\n") + 1, mark.group(1) if mark else None, m.group(2)


def _rel(page: Path) -> str:
    return str(page.relative_to(ROOT))


def test_readme_is_short():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= 200, f"README.md has {n} lines; the details belong on the documentation pages"


def test_pages_are_generated_from_the_committed_results():
    out = subprocess.run([sys.executable, "bench/pages.py", "--check"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr + out.stdout


RUNNER = textwrap.dedent("""
    import sys, traceback
    blocks = {blocks!r}
    ns = {{"__name__": "__main__"}}
    for line, code in blocks:
        try:
            exec(compile(code, f"{page}:{{line}}", "exec"), ns)
        except BaseException:
            traceback.print_exc()
            print(f"FAILED: {page}, the python block at line {{line}}", file=sys.stderr)
            sys.exit(1)
""")

# pages with a python block that is not an excerpt of a file tested elsewhere (``skip``)
PY_PAGES = [p for p in PAGES if any(mark != "skip" for _, mark, _ in blocks(p, {"python"}))]


@pytest.mark.slow
@pytest.mark.parametrize("page", PY_PAGES, ids=_rel)
def test_python_blocks_run(page, tmp_path):
    todo = [(line, code) for line, mark, code in blocks(page, {"python"})
            if mark is None or (mark == "slow" and SLOW)]
    if not todo:
        pytest.skip("every python block of this page is marked skip or slow")
    script = tmp_path / "blocks.py"
    script.write_text(RUNNER.format(blocks=todo, page=_rel(page)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    out = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True,
                         text=True, timeout=900, env=env)
    assert out.returncode == 0, out.stderr[-4000:]


def twinrl_lines():
    for page in PAGES:
        for line, _, code in blocks(page, {"sh", "bash", "shell", "console"}):
            for i, text in enumerate(code.splitlines()):
                words = shlex.split(text, comments=True)
                if words[:1] == ["twinrl"]:
                    yield pytest.param(words[1:], id=f"{_rel(page)}:{line + 1 + i}")


@pytest.mark.parametrize("argv", list(twinrl_lines()))
def test_shell_commands_parse(argv):
    from twinrl.cli import build_parser

    try:
        build_parser().parse_args(argv)
    except SystemExit as e:  # argparse's way of rejecting a command line
        pytest.fail(f"`twinrl {' '.join(argv)}` does not parse (exit {e.code})")


@pytest.mark.slow
def test_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings_handlers.python")
    mkdocs = Path(sys.executable).with_name("mkdocs")
    out = subprocess.run([str(mkdocs), "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=600,
                         env={**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr[-4000:]


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text()
    for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text):
        assert (ROOT / target).exists(), f"README.md links to {target}, which does not exist"
