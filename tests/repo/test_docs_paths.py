"""The docs cite what the repository holds: every repository path a doc names in backticks exists, every dotted
``module.Name`` (and ``module.Class.method``) it names is defined there, the README's "Where to read first" points
at real classes and methods, the README stays a front door (at most 200 lines), and the project's history (commit
hashes, the narrative of how a figure came about) lives only in CHANGELOG.md. Pure file reading: no import of the
project, no process, no network."""

from __future__ import annotations

import ast
import re
import subprocess
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted({ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "deploy" / "README.md", ROOT / "deploy" / "ROBOT.md",
               *ROOT.glob("docs/*.md")})
#: file endings that make a backticked word a path even without a "/"
PATH_ENDINGS = (".py", ".toml", ".md", ".parm", ".service", ".dbc", ".json5")
#: backticked words that look like paths and are not the repository's: what the tools write or read on a user's
#: machine (output directories, a lab's own files named in examples). A new one goes here, deliberately.
NOT_IN_REPO = {
    "demo_out/demo_trajectory.png", "demo_out/demo_pairs.png", "demo_out/pairs.bin", "lab/", "lab/tls/", "lab/state/",
    "station.toml", "driver.toml", "driver-rover1.toml", "demo_fleet.png", "run.mcap", "report/", "fleet.toml",
    "station-router.json5", "robot-client.json5", "station-client.json5", "operator.json5", "trajectory.png",
    "deviation.png", "timeline.png", "report.json", "pairs.png", "mpc_sweep.json", "DIR/mpc_sweep.json",
    "DIR/pairs-POLICY-SEED.bin",
}
README_MAX_LINES = 200


def _prose(text: str) -> str:
    """The text outside fenced blocks (commands and their output are tests/repo/test_docs_commands.py's)."""
    return re.sub(r"```.*?```", "", text, flags=re.S)


def _spans(path: Path) -> list[str]:
    return re.findall(r"`([^`\n]+)`", _prose(path.read_text()))


@cache
def _tracked() -> frozenset[str]:
    """Every file the repository tracks and every directory holding one (the work tree, so new files count)."""
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                         capture_output=True, text=True, check=True, timeout=60).stdout.split()
    found = {f for f in out if (ROOT / f).exists()}
    for f in list(found):
        parts = f.split("/")
        found |= {"/".join(parts[:i]) for i in range(1, len(parts))}
    return frozenset(found)


def _looks_like_path(span: str) -> bool:
    if any(c in span for c in " <>*{}|:$~=,()") or span.startswith(("/", ".", "-", "scm/", "status/")) \
            or span[0].isdigit():
        return False  # a command, a placeholder, a Zenoh key (or its tail) or endpoint, a host's absolute path, a URL,
        # a formula
    return "/" in span or span.endswith(PATH_ENDINGS)


def _exists(span: str) -> bool:
    """A path from the repository's root; a bare file name (``wire.py`` in a row about ``bridge/core/``) or a
    path inside a package (``scm/`` in a row about ``transfer/``) is found where some tracked path ends with it."""
    name = span.rstrip("/")
    tracked = _tracked()
    if name in tracked:
        return True
    first = name.split("/", 1)[0]
    if first in {p.split("/", 1)[0] for p in tracked}:
        return False  # rooted at a top-level entry: it must be exactly there (bridge/wire.py is not bridge/core/)
    return any(p.endswith("/" + name) for p in tracked)


def cited_paths() -> list[tuple[str, str]]:
    return [(str(doc.relative_to(ROOT)), s) for doc in DOCS if doc.exists() for s in _spans(doc)
            if _looks_like_path(s) and s not in NOT_IN_REPO]


def test_the_docs_cite_paths() -> None:
    assert len(cited_paths()) >= 50


@pytest.mark.parametrize(("doc", "span"), cited_paths())
def test_every_cited_path_exists(doc: str, span: str) -> None:
    assert _exists(span), f"{doc} cites `{span}`, which the repository does not hold"


# --- dotted names -------------------------------------------------------------------------------------------------

PACKAGES = ("transfer", "bridge", "drivers", "sim_learner", "bench")


def _module_file(dotted: str) -> Path | None:
    base = ROOT.joinpath(*dotted.split("."))
    for f in (base.with_suffix(".py"), base / "__init__.py"):
        if f.is_file():
            return f
    return None


def _defined(tree: ast.AST) -> dict[str, ast.AST | None]:
    """The names a module or class body defines (functions, classes, assignments, imports), with their node."""
    out: dict[str, ast.AST | None] = {}
    for node in getattr(tree, "body", []):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out[node.name] = node
        elif isinstance(node, ast.Assign):
            out.update({t.id: None for t in node.targets if isinstance(t, ast.Name)})
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            out[node.target.id] = None
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            out.update({(a.asname or a.name).split(".")[0]: None for a in node.names})
    return out


def resolve(dotted: str) -> str | None:
    """None if ``dotted`` (``pkg.module.Name[.attr]``) names something the code defines, else what is missing.
    The longest prefix that is a module file is the module; the rest is looked up in its syntax tree (an
    assignment's or an import's attributes are not followed)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        f = _module_file(".".join(parts[:cut]))
        if f is None:
            continue
        node: ast.AST | None = ast.parse(f.read_text())
        for i in range(cut, len(parts)):
            names = _defined(node)
            if parts[i] not in names:
                return f"{'.'.join(parts[:i])} defines no {parts[i]}"
            node = names[parts[i]]
            if node is None:
                break
        return None
    return f"no module {parts[0]}"


#: ``pkg.module.Name`` (optionally called, ``(...)``) for a package of the project
DOTTED = re.compile(r"((?:" + "|".join(PACKAGES) + r")(?:\.[A-Za-z_]\w*)+)(?:\(.*\))?")


def cited_names() -> list[tuple[str, str]]:
    out = []
    for doc in DOCS:
        if not doc.exists():
            continue
        for s in _spans(doc):
            m = DOTTED.fullmatch(s)
            if m:
                out.append((str(doc.relative_to(ROOT)), m.group(1)))
    return out


@pytest.mark.parametrize(("doc", "dotted"), cited_names())
def test_every_cited_name_is_defined(doc: str, dotted: str) -> None:
    assert resolve(dotted) is None, f"{doc} cites `{dotted}`: {resolve(dotted)}"


def _section(text: str, title: str) -> str:
    m = re.search(r"^## " + re.escape(title) + r"\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
    assert m, f"README.md has no section '## {title}'"
    return m.group(1)


def test_read_first_points_at_real_code() -> None:
    """Each item of the README's "Where to read first" names a file or directory that exists, and every
    ``Class.method`` on its line is defined in that line's file."""
    items = [ln for ln in _section((ROOT / "README.md").read_text(), "Where to read first").splitlines()
             if re.match(r"\s*(\d+\.|-)\s", ln)]
    assert len(items) >= 4, items
    for item in items:
        spans = re.findall(r"`([^`]+)`", item)
        paths = [s for s in spans if _looks_like_path(s)]
        assert paths, f"a read-first item names no file: {item}"
        for p in paths:
            assert (ROOT / p).exists(), f"read first: {p} does not exist"
        for meth in (s for s in spans if re.fullmatch(r"[A-Z]\w*\.\w+", s)):
            cls, name = meth.split(".")
            files = [ROOT / p for p in paths if p.endswith(".py")]
            assert files, f"{item}: `{meth}` with no .py file on its line"
            found = False
            for f in files:
                node = _defined(ast.parse(f.read_text())).get(cls)
                found |= isinstance(node, ast.ClassDef) and name in _defined(node)
            assert found, f"read first: {meth} is not defined in {', '.join(map(str, files))}"


def test_readme_is_a_front_door() -> None:
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines (at most {README_MAX_LINES}: details go to docs/)"


# --- history lives in CHANGELOG.md --------------------------------------------------------------------------------

@cache
def _commits() -> frozenset[str]:
    out = subprocess.run(["git", "log", "--all", "--format=%H"], cwd=ROOT, capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    return frozenset(out)


def _is_commit(word: str) -> bool:
    return any(h.startswith(word.lower()) for h in _commits())


HISTORY = re.compile(r"this sitting|this round|\bseries \d+|\bseries of this", re.I)


@pytest.mark.parametrize("doc", [d for d in DOCS if d.name != "CHANGELOG.md"], ids=lambda d: str(d.relative_to(ROOT)))
def test_history_lives_in_the_changelog(doc: Path) -> None:
    text = doc.read_text()
    hashes = [w for w in re.findall(r"\b[0-9a-f]{7,40}\b", text) if re.search(r"[a-f]", w) and _is_commit(w)]
    assert not hashes, f"{doc.name} names commits {hashes}: commit hashes belong in CHANGELOG.md"
    narrative = HISTORY.findall(text)
    assert not narrative, f"{doc.name} says {narrative}: the history of a figure belongs in CHANGELOG.md"


def test_the_checks_catch_what_they_claim() -> None:
    """The detectors themselves: a moved module, a missing method, a commit hash."""
    assert not _exists("bridge/wire.py") and _exists("bridge/core/wire.py") and _exists("wire.py")
    assert not _looks_like_path("scm/<robot>/cmd") and not _looks_like_path("https://x/y")
    assert resolve("bridge.nodes.station_core.StationCore.tick") is None
    assert resolve("bridge.nodes.station_core.StationCore.nope") is not None
    assert _is_commit(next(iter(_commits()))[:7])


# --- links between the documents ----------------------------------------------------------------------------------

def cited_links() -> list[tuple[str, str]]:
    """Every relative Markdown link and image (``[text](target)``, ``![alt](target)``) of the checked docs."""
    out = []
    for doc in DOCS:
        if doc.exists():
            for target in re.findall(r"\]\(([^)\s]+)\)", _prose(doc.read_text())):
                if "://" not in target and not target.startswith(("#", "mailto:")):
                    out.append((str(doc.relative_to(ROOT)), target))
    return out


def test_the_docs_link_to_each_other() -> None:
    links = cited_links()
    assert len(links) >= 20
    shown = {((ROOT / d).parent / t).resolve() for d, t in links}
    unshown = [f.name for f in sorted((ROOT / "docs" / "figures").glob("*.png")) if f.resolve() not in shown]
    assert not unshown, f"figures no document shows: {unshown}"


@pytest.mark.parametrize(("doc", "target"), cited_links())
def test_every_relative_link_resolves(doc: str, target: str) -> None:
    path = (ROOT / doc).parent / target.split("#", 1)[0]
    assert path.exists(), f"{doc} links to {target}, which is not there ({path.relative_to(ROOT)})"
