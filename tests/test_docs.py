"""The front door and the manual: links and paths that exist, no tracker numbers, a short README,
and README numbers that are the generated results file's."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MANUAL = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]
DATED = [ROOT / "research" / "README.md", *sorted((ROOT / "research" / "notes").glob("*.md")), *sorted((ROOT / "research" / "measurements").glob("*/README.md"))]
TOP = ("stdr/", "docs/", "research/", "scripts/", "tests/", ".ci/")
LINK = re.compile(r"\]\(([^)\s]+)\)")
CODE = re.compile(r"`([^`\s]+)`")


def _relative_links(md: Path):
    for target in LINK.findall(md.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        yield target.split("#")[0]


def _repo_paths(md: Path):
    """Backticked tokens that name a file (with its extension) or a folder (with a trailing /) of
    this repository, without placeholders; a test id's ::name and a :line suffix are dropped.
    (`stdr/phase` is a TensorBoard tag, not a path.)"""
    for tok in CODE.findall(md.read_text()):
        tok = re.sub(r":\d+(-\d+)?$", "", tok.split("::")[0].rstrip(".,;"))
        if (tok.startswith(TOP) and not re.search(r"[<>*{}\[\]$]|\.\.\.|…", tok)
                and (tok.endswith("/") or re.search(r"\.[A-Za-z]+$", tok))):
            yield tok


@pytest.mark.parametrize("md", MANUAL, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_and_repository_path_exists(md):
    missing = [t for t in _relative_links(md) if not (md.parent / t).exists()]
    missing += [t for t in _repo_paths(md) if not (ROOT / t).exists()]
    assert missing == [], f"{md.relative_to(ROOT)} names paths that do not exist: {missing}"


@pytest.mark.parametrize("md", DATED, ids=lambda p: str(p.relative_to(ROOT)))
def test_notes_and_study_readmes_link_to_what_exists(md):
    missing = [t for t in _relative_links(md) if not (md.parent / t).exists()]
    assert missing == [], f"{md.relative_to(ROOT)} links to paths that do not exist: {missing}"


def test_docs_holds_the_manual_and_research_the_records():
    """docs/ is the manual: its pages, their images and the generated results page. Measurement
    records and dated notes live under research/, outside the package."""
    files = subprocess.run(["git", "ls-files", "docs", "research"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    if not files:
        pytest.skip("not a git checkout")
    docs = [f for f in files if f.startswith("docs/")]
    stray = [f for f in docs if not re.fullmatch(r"docs/[a-z_]+\.md|docs/images/[\w.-]+\.(png|jpg|svg|gif)", f)]
    assert stray == [] and len(docs) <= 40, stray or len(docs)
    assert any(f.startswith("research/measurements/") for f in files) and "research/README.md" in files


#: words about how the work on the software was organized, not about the software
PROCESS = re.compile(r"\b(the|this|a|each|next|last|that) session\b|\bthe issue\b|\blent\b|device time|"
                     r"peers\.md|review\.md|\.\./shared/(reference|data)", re.IGNORECASE)


@pytest.mark.parametrize("md", [m for m in MANUAL if m.name != "CHANGELOG.md"], ids=lambda p: str(p.relative_to(ROOT)))
def test_the_manual_speaks_of_the_software_and_its_users(md):
    hits = [m.group(0) for m in PROCESS.finditer(md.read_text())]
    assert hits == [], f"{md.relative_to(ROOT)}: {hits}"


def test_no_issue_tracker_numbers_in_the_docs():
    """A reader cannot resolve the tracker's numbers: each says the decision it stands for."""
    pat = re.compile(r"issues? ?#?[0-9]+", re.IGNORECASE)
    hits = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in MANUAL + DATED for m in pat.finditer(p.read_text())]
    assert hits == []


# the README's test command, which .ci/run runs exactly
TEST_CMD = "bash scripts/setup.sh && scripts/run.sh python -m pytest -q -n 2 --dist loadfile"


def test_the_readme_is_a_front_door():
    lines = (ROOT / "README.md").read_text().split("\n")
    assert len(lines) <= 150
    first = "\n".join(lines[:40])
    assert "bash scripts/setup.sh && scripts/run.sh stdr-train" in first
    assert TEST_CMD in first
    # .ci/run runs the README's test command
    assert TEST_CMD in (ROOT / ".ci" / "run").read_text()


def test_the_numbers_the_readme_quotes_are_the_generated_ones():
    """README.md's results and demo blocks and docs/results.md are what studies/results.py makes
    from the committed records now (a hand edit, or a record added without regenerating, fails)."""
    r = subprocess.run([sys.executable, "-m", "studies.results", "--check"], cwd=ROOT, capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr + r.stdout
