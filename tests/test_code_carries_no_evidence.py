"""The packages' comments and docstrings say what the code does and why, never the evidence or history.

Measured numbers live in ``docs/claims`` and the studies under ``results/``, the history in
``CHANGELOG.md`` and git: a comment that cites a run, an issue or a version goes stale as soon as the
run is redone or the version passes. This test reads every comment and docstring (any string that
stands alone as a statement) of the three packages' ``.py`` files, and the comments of the shipped
``zoo_configs/*.yml``, and fails naming ``file:line`` for each forbidden phrase.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sb3_divmorph", "divmorph", "unimal_envs")

#: ``results/<name>`` paths that are part of a feature's interface, not evidence: the shipped run
#: (``load_pretrained("results/cpu100/teachers/FT")``, ``divmorph fetch-models cpu100``), the layout
#: ``fetch-models`` reads in a checkout (``results/<run>/``) and the gallery's default output.
INTERFACE_RESULTS = {"cpu100", "<run>", "tasks.png"}
#: Files that are about the shipped run itself, where its name is the subject.
RUN_NAME_FILES = {"divmorph/shipped.py", "divmorph/cli/fetch_models.py"}

FORBIDDEN = [
    ("an issue number", re.compile(r"\b(issue|pull request|PR)s?\s*#?\d+|(?<![\w&/])#\d+\b", re.I)),
    ("a claims page", re.compile(r"docs/claims", re.I)),
    ("a version's history", re.compile(r"\b(before|since|until|after|prior to|pre-)\s*(divmorph\s+)?v?\d+\.\d+", re.I)),
    ("a version's history", re.compile(r"\bdivmorph\s+v?\d+\.\d+|\bin\s+v?\d+\.\d+\.\d+\b", re.I)),
    (
        "a version's history",
        re.compile(
            r"\bolder runs?\b|\bpre-arms\b|stays? comparable|\bwas\s[^.;]{0,40}\buntil\b|\bearlier versions?\b|"
            r"\bused to be\b|\bformerly\b|\bbefore\s[^.;]{0,30}\bexisted\b|\bretired (in|since)\b|\bretired since\b",
            re.I,
        ),
    ),
]
RESULTS_PATH = re.compile(r"\bresults/([\w.<>{}-]+)")
RUN_NAME = re.compile(r"(?<![/\w-])cpu100\b")


def python_prose(path: Path) -> list[tuple[int, str]]:
    """``[(line, text)]`` of every comment and every string standing alone as a statement (docstrings)."""
    source = path.read_text()
    found = [
        (token.start[0], token.string) for token in tokenize.generate_tokens(io.StringIO(source).readline) if token.type == tokenize.COMMENT
    ]
    for node in ast.walk(ast.parse(source, filename=str(path))):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            found += [(node.lineno + i, line) for i, line in enumerate(ast.get_source_segment(source, node).splitlines())]
    return sorted(found)


def yaml_comments(path: Path) -> list[tuple[int, str]]:
    """``[(line, text)]`` of the comments of a YAML file (from a ``#`` at the start or after a blank)."""
    found = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        match = re.search(r"(?:^|\s)(#.*)$", line)
        if match:
            found.append((number, match.group(1)))
    return found


def problems(relative: str, prose: list[tuple[int, str]], python: bool) -> list[str]:
    """``file:line: what -- text`` for each forbidden phrase in ``prose``."""
    found = []
    for number, text in prose:
        body = re.sub(r"^#+:?", "", text.strip())  # the comment's own marker is no issue number
        said = [what for what, pattern in FORBIDDEN if pattern.search(body)]
        said += [f"a result path (results/{m})" for m in RESULTS_PATH.findall(body) if m.rstrip("/.") not in INTERFACE_RESULTS]
        if python and relative not in RUN_NAME_FILES and RUN_NAME.search(RESULTS_PATH.sub("", body)):
            said.append("a run's name")
        found += [f"{relative}:{number}: {what} -- {text.strip()}" for what in dict.fromkeys(said)]
    return found


def test_the_packages_comments_and_docstrings_carry_no_evidence_or_history():
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            found += problems(relative, python_prose(path), python=True)
    for path in sorted((ROOT / "zoo_configs").glob("*.yml")):
        found += problems(path.relative_to(ROOT).as_posix(), yaml_comments(path), python=False)
    assert not found, (
        "comments and docstrings that cite results, issues or version history (say what and why; the numbers "
        "belong in docs/claims, the history in CHANGELOG.md and git):\n" + "\n".join(found)
    )


def test_the_check_sees_each_kind_of_evidence(tmp_path):
    # the reader itself: a planted comment, docstring and YAML comment of each kind are found, interface paths are not
    module = tmp_path / "m.py"
    module.write_text(
        '"""Fixed in issue 42; see docs/claims/transfer.md."""\n'
        "x = 1  # the pre-arms seed, so older runs stay comparable\n"
        "def f():\n"
        '    """Loads results/cpu100/teachers/FT (fine); results/cpu-race says 56 (not fine)."""\n'
        "    return 'results/novel-task-gates'  # a string in code is not prose\n"
        "#: the cpu100 student's gates, before divmorph 0.2\n"
    )
    config = tmp_path / "c.yml"
    config.write_text("a: 1  # from results/cpu-calibration (issue #27)\nb: '#3'\n")
    found = problems("m.py", python_prose(module), python=True) + problems("c.yml", yaml_comments(config), python=False)
    lines = sorted({line.split(": ")[0] for line in found})
    assert lines == ["c.yml:1", "m.py:1", "m.py:2", "m.py:4", "m.py:6"], found
    assert [line.split(" -- ")[0] for line in found if line.startswith("m.py:4")] == ["m.py:4: a result path (results/cpu-race)"]
    assert sum("m.py:1" in line for line in found) == 2  # the issue and the claims page
