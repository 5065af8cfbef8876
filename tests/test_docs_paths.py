"""Every repository path and module name that the README and docs/ name exists.

The documents checked are README.md and docs/*.md. CHANGELOG.md is left out: it records what was
true when each change was made, paths included. benchmarks/README.md is a log of measurements,
each with the commit it was taken at, and is left out too.

Which mentions count, exactly:

- Where: inside code, that is inline code spans (`...`, which may wrap a line) and fenced code
  blocks (```...```), and in the targets of Markdown links, [text](target). Prose outside code
  and indented code blocks are not read: a path a reader is meant to find is put in backticks or
  a link.
- Link targets: every target that is not a URL (scheme://, mailto:) or an anchor alone (#...) is a
  path relative to the document's own folder, its #anchor dropped, and must exist.
- Paths in code: the text is cut into tokens at white space and at the characters ( ) [ ] { } , ;
  " ' = and a token counts as a repository path when
    (a) its first /-separated part is one of TOP_LEVEL, the repository's top-level entries
        (spherejax/, hw/, tests/, benchmarks/, docs/, constraints/, .ci/ and the files setup.py,
        pyproject.toml, README.md, CHANGELOG.md): `hw/profile.py`, `spherejax/_engine/kernel/`,
        `tests/data/`, `setup.py`; it must exist as written, relative to the repository root; or
    (b) it has no / and ends in .py, .cc or .h (a bare source file name: `conftest.py`): some
        file of that name must exist under TOP_LEVEL's folders.
  A token with * is a glob (`bench_*.py`, `benchmarks/bench_*.py`) and must match at least one
  file. Output paths and examples (`OUT/manifest.jsonl`, `spherejax-demo/evaluation/tables.txt`,
  `~/.cache/spherejax`, `.venv/bin/python`, `/dev/ttyUSB0`, `cal.h5`) start with no top-level
  entry and have no source extension, so they do not count.
- Module names in code: every dotted name that starts with spherejax., spherejax_hw. or sj. (the
  README's alias for spherejax) must resolve: the longest importable module prefix is imported
  and the rest looked up as attributes (`spherejax.io.SpherejaxFileError`, `sj.plan`). A name
  followed by * (`sj.QUALITY_*`) needs some attribute with that prefix.

The test reports every missing mention with its document and line.
"""

from __future__ import annotations

import fnmatch
import importlib
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: The repository's top-level entries a path may start with (folders end in /).
TOP_LEVEL = ("spherejax/", "hw/", "tests/", "benchmarks/", "docs/", "constraints/", ".ci/",
             "setup.py", "pyproject.toml", "README.md", "CHANGELOG.md")
#: Bare names with these endings are source files of the repository.
SOURCE_SUFFIXES = (".py", ".cc", ".h")

DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)
_SPAN = re.compile(r"`([^`]+)`")
_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
_SPLIT = re.compile(r"[\s()\[\]{},;\"'=]+")
_DOTTED = re.compile(r"(?<![\w.])(spherejax_hw|spherejax|sj)((?:\.[A-Za-z_]\w*)+)(\*?)")


def _code(text: str) -> list[tuple[int, str]]:
    """(line number, code) for each fenced block and inline span of `text`."""
    found = []
    blanked = list(text)
    for match in _FENCE.finditer(text):
        found.append((text.count("\n", 0, match.start(1)) + 1, match.group(1)))
        blanked[match.start():match.end()] = " " * (match.end() - match.start())
    rest = "".join(blanked)
    for match in _SPAN.finditer(rest):
        found.append((rest.count("\n", 0, match.start()) + 1, match.group(1)))
    return found


def _links(text: str) -> list[tuple[int, str]]:
    return [(text.count("\n", 0, m.start()) + 1, m.group(1)) for m in _LINK.finditer(text)]


_FOLDERS = tuple(name for name in TOP_LEVEL if name.endswith("/"))
_FILES = tuple(name for name in TOP_LEVEL if not name.endswith("/"))


def _repository_files() -> list[pathlib.Path]:
    files = [ROOT / name for name in _FILES]
    for folder in _FOLDERS:
        files += [path for path in (ROOT / folder).rglob("*") if path.is_file()
                  and not any(part == "__pycache__" or part.endswith(".egg-info") for part in path.parts)]
    return files


def _is_repository_path(token: str) -> bool:
    """Rule (a) or (b) of the module docstring."""
    if "/" in token:
        return token.split("/", 1)[0] + "/" in _FOLDERS
    return token in _FILES or token.endswith(SOURCE_SUFFIXES)


def _exists(token: str, names: set[str], relative: set[str]) -> bool:
    if "/" in token or token in _FILES:
        if "*" in token:
            return any(fnmatch.fnmatchcase(path, token.rstrip("/")) for path in relative)
        return (ROOT / token).exists()
    if "*" in token:
        return any(fnmatch.fnmatchcase(name, token) for name in names)
    return token in names


def _resolves(head: str, tail: str, star: str) -> bool:
    parts = tail.lstrip(".").split(".")
    module_name = "spherejax" if head == "sj" else head
    obj = importlib.import_module(module_name)
    index = 0
    # The longest importable module prefix, then attributes.
    for i in range(len(parts), 0, -1):
        candidate = ".".join([module_name, *parts[:i]])
        try:
            obj = importlib.import_module(candidate)
        except ImportError:
            continue
        index = i
        break
    for j, name in enumerate(parts[index:], index):
        last = j == len(parts) - 1
        if last and star:
            return any(attribute.startswith(name) for attribute in dir(obj))
        if not hasattr(obj, name):
            return False
        obj = getattr(obj, name)
    return True


def _problems(text: str, where: str, folder: pathlib.Path) -> list[str]:
    """What `text` (the document `where`, in `folder`) names that does not exist, a line each."""
    files = _repository_files()
    names = {path.name for path in files}
    relative = {path.relative_to(ROOT).as_posix() for path in files}
    problems = []
    for line, target in _links(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue
        path = target.split("#", 1)[0]
        if path and not (folder / path).exists():
            problems.append(f"{where}:{line}: link to {target}, which does not exist")
    for line, code in _code(text):
        for token in _SPLIT.split(code):
            token = token.rstrip(".:")
            if token and _is_repository_path(token) and not _exists(token, names, relative):
                problems.append(f"{where}:{line}: {token} does not exist")
        for match in _DOTTED.finditer(code):
            head, tail, star = match.groups()
            if not _resolves(head, tail, star):
                problems.append(f"{where}:{line}: {head}{tail}{star} does not resolve")
    return problems


def test_the_top_level_entries_exist():
    """TOP_LEVEL is the list the other checks rely on: each entry must be there."""
    assert [name for name in TOP_LEVEL if not (ROOT / name).exists()] == []
    assert {p.name for p in DOCUMENTS} >= {"README.md", "design.md"}


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_path_and_module_a_document_names_exists(document):
    text = document.read_text(encoding="utf-8")
    assert _problems(text, document.relative_to(ROOT).as_posix(), document.parent) == []


@pytest.mark.parametrize("text, expected", [
    # Counted: paths from a top-level entry, bare source names, globs, links.
    ("See `hw/profile.py`.", []),
    ("See `hw/no_such_module.py`.", ["hw/no_such_module.py does not exist"]),
    ("See `spherejax/_engine/kernel/fused_correct.cc`.", ["spherejax/_engine/kernel/fused_correct.cc does not exist"]),
    ("Run\n```\npython benchmarks/bench_nothing.py --size 8\n```\n", ["benchmarks/bench_nothing.py does not exist"]),
    ("`conftest.py` and `no_such_file.cc`", ["no_such_file.cc does not exist"]),
    ("`benchmarks/bench_*.py` and `bench_*.py`", []),
    ("`benchmarks/zzz_*.py`", ["benchmarks/zzz_*.py does not exist"]),
    ("[design](design.md) and [gone](gone.md#anchor)", ["link to gone.md#anchor, which does not exist"]),
    ("`setup.py`, `pyproject.toml`, `tests/data/`, `.ci/run`", []),
    # Not counted: outputs, examples, URLs, prose.
    ("`OUT/manifest.jsonl`, `spherejax-demo/evaluation/tables.txt`, `~/.cache/spherejax`, `/dev/ttyUSB0`", []),
    ("`.venv/bin/python`, `cal.h5`, `frames/<id>.tif`, [site](https://example.org/x.md)", []),
    ("in prose spherejax/missing.py is not read", []),
    # Module names.
    ("`spherejax.io.SpherejaxFileError`, `sj.plan(calibration, shape)`, `sj.QUALITY_*`", []),
    ("`spherejax.no_such_module`", ["spherejax.no_such_module does not resolve"]),
    ("`sj.no_such_name(x)`", ["sj.no_such_name does not resolve"]),
    ("`sj.NO_SUCH_*`", ["sj.NO_SUCH_* does not resolve"]),
])
def test_which_mentions_count(text, expected):
    """The rules of the module docstring on small documents, read as if they were in docs/: a
    mention that counts and does not exist is reported, one that does not count never is."""
    problems = [problem.split(": ", 1)[1] for problem in _problems(text, "probe.md", ROOT / "docs")]
    assert problems == expected
